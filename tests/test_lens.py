"""The simulator's fisheye lens: the same model as OpenCV's cv2.fisheye, rendered by warping a
wider pinhole render, its keys validated, its draws after every earlier one (docs/SIM.md)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import pytest

from jetbot_rt.calibration.intrinsics import Lens
from jetbot_rt.config.sections import Config, load_config
from jetbot_rt.errors import UsageError

LENSES = [Lens(), Lens(0.95, (0.48, 0.52), (0.05, -0.02, 0.0, 0.0)),
          Lens(1.1, (0.5, 0.5), (-0.04, 0.01, 0.003, -0.002))]


@pytest.mark.parametrize("lens", LENSES)
@pytest.mark.parametrize("size", [(56, 56), (640, 360)])
def test_each_pixels_ray_lands_on_that_pixel_through_opencvs_fisheye_model(
        lens: Lens, size: tuple[int, int]) -> None:
    width, height = size
    x, y = lens.rays(width, height)
    rays = np.stack([x.ravel(), y.ravel(), np.ones(x.size)], axis=1).reshape(1, -1, 3)
    pixels, _ = cv2.fisheye.projectPoints(rays, np.zeros((3, 1)), np.zeros((3, 1)),
                                          lens.matrix(width, height), lens.distortion())
    u, v = np.meshgrid(np.arange(width), np.arange(height))
    assert np.abs(pixels.reshape(-1, 2) - np.stack([u.ravel(), v.ravel()], 1)).max() < 1e-6


def test_a_lens_that_folds_back_or_sees_past_80_degrees_is_refused_in_one_line() -> None:
    with pytest.raises(UsageError, match="lens") as folded:
        Lens(1.0194, k=(-0.5, 0.0, 0.0, 0.0)).rays(64, 36)
    assert "\n" not in str(folded.value)
    with pytest.raises(UsageError, match="80"):
        Lens(0.3).rays(64, 36)  # the frame's corner would be ~155 degrees from the axis


@pytest.mark.parametrize("table, says", [
    ('lens = "fish"', "lens"), ("lens_k1 = 2.0", "lens_k1"), ("lens_focal = 0.0", "lens_focal"),
    ("lens_center = [0.5]", "lens_center"), ("lens_center = [0.9, 0.5]", "lens_center"),
])
def test_bad_lens_keys_are_refused_by_the_schema(tmp_path: Path, table: str, says: str) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(f"[sim]\n{table}\n")
    with pytest.raises(UsageError, match=says):
        load_config(str(path))


def test_the_lens_draws_come_after_every_earlier_draw_of_a_seed() -> None:
    from jetbot_rt.sim.randomize import params, sample

    config = Config()
    fixed = dataclasses.replace(config.randomize, lens_focal=[1.0, 1.0], lens_k1=[0.0, 0.0],
                                lens_k2=[0.0, 0.0])
    for seed in range(5):
        drawn = params(sample(config.sim, config.randomize, np.random.default_rng(seed)))
        plain = params(sample(config.sim, fixed, np.random.default_rng(seed)))
        lens_keys = {"lens_focal", "lens_k1", "lens_k2"}
        assert {k: v for k, v in drawn.items() if k not in lens_keys} == \
               {k: v for k, v in plain.items() if k not in lens_keys}
        assert plain["lens_focal"] == config.sim.lens_focal and plain["lens_k1"] == 0.0
    measured = dataclasses.replace(config.sim, lens_k1=0.2)  # an offset draw keeps its centre
    k1 = [sample(measured, config.randomize, np.random.default_rng(s)).lens_k1 for s in range(20)]
    assert all(0.17 <= v <= 0.23 for v in k1) and len(set(k1)) > 1


def test_the_fisheye_renders_a_wider_view_with_the_centre_where_the_pinhole_has_it() -> None:
    pytest.importorskip("pybullet")
    from jetbot_rt.sim.config import SimConfig
    from jetbot_rt.sim.world import JetbotWorld

    def red(image: np.ndarray) -> np.ndarray:
        r, g, b = (image[..., i].astype(int) for i in range(3))
        return np.argwhere((r > 120) & (g < 60) & (b < 60))

    views = {}
    for lens in ("pinhole", "fisheye"):
        with JetbotWorld(SimConfig(lens=lens), image_size=(160, 90)) as world:
            world.reset(block_xy=(0.0, 0.0))  # 0.6 m straight ahead, at the image's centre
            views[lens] = world.render()
            assert views[lens].shape == (90, 160, 3)
    pinhole, fisheye = red(views["pinhole"]), red(views["fisheye"])
    # the block: at the same column (centre), a little smaller through the fisheye (its
    # centre is ~7 degrees down, where the fisheye shows ~1 % less than the matched pinhole)
    assert abs(pinhole[:, 1].mean() - fisheye[:, 1].mean()) < 0.6
    assert 0.85 < len(fisheye) / len(pinhole) < 1.0
    # the walls' corners: the pinhole's 82 degrees show none, the fisheye's 100 do
    assert not np.array_equal(views["pinhole"], views["fisheye"])

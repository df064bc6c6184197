"""The appearance families (issue 26): seeded generators that replay bit for bit, textures that
differ between families, clutter that keeps clear of the task, held-out looks that training
never draws, the keys' validation, and the randomization's earlier draws left as they were."""

from __future__ import annotations

import dataclasses
import itertools
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from jetbot_rt.config.sections import Config, from_dict, load_config
from jetbot_rt.errors import UsageError
from jetbot_rt.sim import textures
from jetbot_rt.sim.camera_look import CameraLook
from jetbot_rt.sim.clutter import CLEARANCE, furniture
from jetbot_rt.sim.config import FLOOR_TEXTURES, SimConfig
from jetbot_rt.sim.look_draws import LOOK_KEYS, held_out, sample_looks
from jetbot_rt.sim.randomize import sample
from jetbot_rt.tasks import load_task
from jetbot_rt.tasks.scene import ROOM_HALF_SIZE, Block

CONDITIONS = Path(__file__).resolve().parent.parent / "benchmarks" / "appearance_conditions"
WOOD = (0.55, 0.4, 0.25)


def test_every_floor_family_replays_bit_for_bit_and_another_seed_draws_another():
    for family in FLOOR_TEXTURES:
        first = textures.floor_texture(family, WOOD, 5)
        assert first.shape == (textures.FLOOR_TEXELS, textures.FLOOR_TEXELS, 3)
        assert first.dtype == np.uint8
        assert np.array_equal(first, textures.floor_texture(family, WOOD, 5)), family
        if family != "checker":  # the checker has nothing to draw
            assert not np.array_equal(first, textures.floor_texture(family, WOOD, 6)), family
    lit = textures.bake_light(textures.floor_texture("plain", WOOD, 1), 2, 1.0, 9)
    assert np.array_equal(lit, textures.bake_light(textures.floor_texture("plain", WOOD, 1),
                                                   2, 1.0, 9))


def test_the_families_differ_from_each_other_and_keep_the_floor_colour():
    images = {f: textures.floor_texture(f, WOOD, 3).astype(np.float32) for f in FLOOR_TEXTURES}
    for a, b in itertools.combinations(FLOOR_TEXTURES, 2):
        assert np.abs(images[a] - images[b]).mean() > 2.0, (a, b)
    base = np.asarray(WOOD) * 255
    for family, image in images.items():
        if family in ("checker", "rug"):  # dark tiles; a rug of other colours
            continue
        assert np.abs(image.mean(axis=(0, 1)) - base).max() < 0.1 * 255, family
    # the structure is the family's: a plain floor is nearly flat, the others are not
    spread = {f: float(image.std(axis=(0, 1)).max()) for f, image in images.items()}
    assert spread["plain"] < 2 < min(v for f, v in spread.items() if f != "plain")
    walls = [textures.wall_texture(s, (0.8, 0.78, 0.7), (0.95, 0.95, 0.95), 4)
             for s in textures.WALL_STYLES]
    for a, b in itertools.combinations(walls, 2):
        assert not np.array_equal(a, b)
    board = round(textures.WALL_TEXELS[1] * textures.SKIRTING_M / textures.WALL_HEIGHT_M)
    assert np.all(walls[0][-board:] == np.uint8(round(0.95 * 255)))


def test_clutter_keeps_clear_of_the_task_and_is_never_the_goals_shape_or_colour():
    seek = load_task("seek")
    placed = 0
    for seed in range(20):
        scene = seek.scene(np.random.default_rng(seed), True)
        pieces = furniture(6, seed, scene)
        assert pieces == furniture(6, seed, scene)  # replays
        placed += len(pieces)
        for piece in pieces:
            r, _, height = piece.size
            extent = (2 * r, 2 * r, height) if piece.kind == "cylinder" else piece.size
            assert min(extent) >= 0.1  # never a 5 cm cube
            assert not textures.goal_like(piece.color)
            turned = abs(np.sin(piece.yaw)) > 0.5  # boxes stand square to their wall
            half = (extent[1] / 2, extent[0] / 2) if turned else (extent[0] / 2, extent[1] / 2)
            assert all(abs(c) + h <= ROOM_HALF_SIZE + 1e-9 for c, h in zip(piece.xy, half))
            for block in (p for p in scene.pieces if isinstance(p, Block)):
                gap = np.linalg.norm(np.subtract(piece.xy, block.xy))
                assert gap >= piece.radius + CLEARANCE
    assert placed >= 60  # the edges have room for most of them


def test_the_held_out_looks_are_never_drawn_by_the_training_randomization():
    ranges = Config().randomize
    rng = np.random.default_rng(26)
    drawn = [sample_looks(SimConfig(), ranges, rng) for _ in range(500)]
    for looks in drawn:
        sim = dataclasses.replace(SimConfig(), **looks)
        assert held_out(sim, ranges) is None, looks
        assert not textures.goal_like(tuple(looks["floor_color"]))
    assert {d["floor_texture"] for d in drawn} == set(ranges.floor_families)
    for key in ("clutter", "lamps", "window_light", "exposure", "gain_noise", "vignetting",
                "motion_blur"):  # every draw within its [randomize] range
        low, high = getattr(ranges, key)
        assert all(low <= d[key] <= high for d in drawn), key
    assert all(ranges.white_balance[0] <= d["white_balance"][i] <= ranges.white_balance[1]
               for d in drawn for i in (0, 2))
    files = sorted(CONDITIONS.glob("*.toml"))
    assert len(files) >= 8
    for path in files:
        config = load_config(path)
        assert config.randomize.enabled is False, path.name
        assert held_out(config.sim, ranges) is not None, path.name


def test_the_families_come_after_every_earlier_draw():
    base, on = SimConfig(), Config().randomize
    off = dataclasses.replace(on, appearance=False)
    for seed in range(5):
        plain = sample(base, off, np.random.default_rng(seed))
        looks = sample(base, on, np.random.default_rng(seed))
        for field in dataclasses.fields(SimConfig):
            if field.name not in LOOK_KEYS:
                assert getattr(plain, field.name) == getattr(looks, field.name), field.name
        for key in ("wall_texture", "clutter", "exposure", "look_seed"):  # off: [sim]'s
            assert getattr(plain, key) == getattr(base, key)


def test_a_randomized_textured_episode_renders_at_the_policy_size_and_replays():
    from jetbot_rt.train.env import JetbotEnv

    config = from_dict({"randomize": {"appearance": True}})
    env = JetbotEnv("seek", config)
    try:
        first, _ = env.reset(seed=3)
        env.step(np.array([1.0, 0.6]))
        moved = env.world.frame().copy()
        again, _ = env.reset(seed=3)
        env.step(np.array([1.0, 0.6]))
        assert first.shape == (56, 56, 3)
        assert np.array_equal(first, again) and np.array_equal(moved, env.world.frame())
        other, _ = env.reset(seed=4)
        assert not np.array_equal(first, other)
        assert env.world.sim.floor_texture in config.randomize.floor_families
    finally:
        env.close()


def test_the_camera_look_exposes_vignettes_and_blurs_only_while_moving():
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (56, 56, 3), dtype=np.uint8)
    sim = SimConfig()
    assert CameraLook(sim, (56, 56)).apply(image) is image  # off: untouched
    blur = CameraLook(dataclasses.replace(sim, motion_blur=0.03), (56, 56))
    still, turning = blur.apply(image), blur.apply(image, yaw_rate=3.0)
    assert np.abs(still.astype(int) - image).max() <= 1  # the gamma round trip only
    assert np.abs(np.diff(turning.astype(int), axis=1)).mean() < 0.7 * np.abs(
        np.diff(image.astype(int), axis=1)).mean()
    grey = np.full((56, 56, 3), 128, np.uint8)
    vignette = CameraLook(dataclasses.replace(sim, vignetting=0.5), (56, 56)).apply(grey)
    assert vignette[0, 0, 0] < vignette[28, 28, 0] - 20
    bright = CameraLook(dataclasses.replace(sim, exposure=2.0, white_balance=[1.2, 1.0, 0.8]),
                        (56, 56)).apply(grey)
    assert bright[..., 0].mean() > bright[..., 1].mean() > bright[..., 2].mean() > 128
    noisy = dataclasses.replace(sim, gain_noise=0.05, seed=7)
    assert np.array_equal(CameraLook(noisy, (56, 56)).apply(grey),
                          CameraLook(noisy, (56, 56)).apply(grey))


@pytest.mark.parametrize(("table", "message"), [
    ({"sim": {"floor_texture": "marble"}}, "[sim] floor_texture must be one of"),
    ({"sim": {"clutter": 40}}, "[sim] clutter must be"),
    ({"randomize": {"floor_families": []}}, "[randomize] floor_families must be"),
    ({"randomize": {"heldout_floor_hsv": [10, 5, 0, 1, 0, 1]}},
     "[randomize] heldout_floor_hsv must be"),
])
def test_bad_look_keys_are_refused_in_one_line(table, message):
    with pytest.raises(UsageError) as raised:
        from_dict(table)
    assert message in str(raised.value) and "\n" not in str(raised.value)


def test_a_bad_look_key_in_a_config_file_is_one_line_and_exit_2(tmp_path: Path):
    config = tmp_path / "bad.toml"
    config.write_text('[sim]\nwall_texture = "brick"\n')
    done = subprocess.run(  # the robot side's command: the same schema, a light import
        [str(Path(sys.executable).with_name("jetbot-rt")), "check", "--config", str(config)],
        capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 2
    assert done.stderr.count("\n") == 1 and "[sim] wall_texture must be one of" in done.stderr

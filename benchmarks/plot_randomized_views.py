"""Look at what domain randomization does to the camera.

- docs/images/randomized_views.png: the ideal view and randomized draws of today's ranges
  (the forward task's start, 224x224 and the trainer's 64x64).
- docs/images/appearance_views.png: the appearance families (issue 26) on the seek task's
  start: each floor family once (top row), then draws of ``[randomize] appearance = true``
  at 224x224 and, below them, the same draws at the policy's 56x56.

Run: .venv/bin/python benchmarks/plot_randomized_views.py
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from jetbot_rt.config.sections import from_dict
from jetbot_rt.train.env import JetbotEnv

IMAGES = Path(__file__).resolve().parent.parent / "docs" / "images"
SEEDS = [0, 1, 2, 3, 4, 5, 6]
FAMILIES: dict[str, dict[str, Any]] = {
    "checker": {"floor_texture": "checker"},
    "plain": {"floor_texture": "plain", "floor_color": [0.55, 0.55, 0.52]},
    "wood": {"floor_texture": "wood", "floor_color": [0.55, 0.38, 0.22]},
    "carpet": {"floor_texture": "carpet", "floor_color": [0.62, 0.58, 0.5]},
    "tiles": {"floor_texture": "tiles", "floor_color": [0.78, 0.77, 0.74]},
    "rug": {"floor_texture": "rug", "floor_color": [0.6, 0.45, 0.3]},
    "concrete": {"floor_texture": "concrete", "floor_color": [0.55, 0.55, 0.55]},
}
"""Each family in a typical colour, with skirting, clutter and a lamp (seed 2)."""
ROOM = {"wall_color": [0.86, 0.84, 0.78], "wall_texture": "paint", "look_seed": 2,
        "skirting_color": [0.95, 0.95, 0.93], "clutter": 4, "lamps": 1}


def view(task: str, sim: dict[str, Any], randomize: dict[str, Any] | None, seed: int,
         size: tuple[int, int]) -> tuple[Any, Any]:
    config = from_dict({"actions": {"max_speed": 0.4}, "sim": sim,
                        "randomize": randomize or {}})
    env = JetbotEnv(task, config, randomize=randomize is not None, image_size=size)
    try:
        obs, _ = env.reset(seed=seed, options={"start_noise": False})
        return obs, env.world.sim
    finally:
        env.close()


def blank(ax: Any) -> None:
    ax.set_xticks([])
    ax.set_yticks([])


def today() -> None:
    fig, axes = plt.subplots(2, len(SEEDS) + 1, figsize=(2.2 * (len(SEEDS) + 1), 4.8))
    for row, size in enumerate([(224, 224), (64, 64)]):
        for col, seed in enumerate([None, *SEEDS]):
            obs, s = view("forward", {}, None if seed is None else {}, seed or 0, size)
            ax = axes[row, col]
            ax.imshow(obs)
            blank(ax)
            if seed is None:
                ax.set_title(f"ideal {size[0]}px", fontsize=8)
            else:
                ax.set_title(
                    f"seed {seed}: gain {s.wheel_gain[0]:.2f}/{s.wheel_gain[1]:.2f}\n"
                    f"pitch {s.camera_pitch_deg:.0f} fov {s.camera_vfov_deg:.0f} "
                    f"light {s.light_intensity:.2f}", fontsize=6)
    fig.tight_layout()
    out = IMAGES / "randomized_views.png"
    fig.savefig(out, dpi=110)
    print(out)


def families(draws: int = 7) -> None:
    columns = max(len(FAMILIES), draws)
    fig, axes = plt.subplots(3, columns, figsize=(2.2 * columns, 7.4))
    for col, (name, sim) in enumerate(FAMILIES.items()):
        obs, _ = view("seek", {**ROOM, **sim}, None, 1, (224, 224))
        axes[0, col].imshow(obs)
        axes[0, col].set_title(f"{name} (fixed [sim])", fontsize=8)
    for col in range(draws):
        seed = 100 + col
        for row, size in ((1, (224, 224)), (2, (56, 56))):
            obs, s = view("seek", {}, {"appearance": True}, seed, size)
            axes[row, col].imshow(obs)
            if row == 1:
                axes[row, col].set_title(
                    f"seed {seed}: {s.floor_texture}, {s.wall_texture} walls\n"
                    f"clutter {s.clutter} lamps {s.lamps} shadows {'on' if s.shadows else 'off'}"
                    f"\nexposure {s.exposure:.2f} blur {1000 * s.motion_blur:.0f} ms",
                    fontsize=6)
            else:
                axes[row, col].set_title("the same at 56x56 (the policy's)", fontsize=6)
    for ax in axes.flat:
        blank(ax)
    fig.tight_layout()
    out = IMAGES / "appearance_views.png"
    fig.savefig(out, dpi=100)
    print(out)


def main() -> None:
    IMAGES.mkdir(parents=True, exist_ok=True)
    today()
    families()


if __name__ == "__main__":
    main()

"""Look at what domain randomization does to the camera: the ideal view and randomized draws
(the forward task's start, 224x224 and the trainer's 64x64). Writes
docs/images/randomized_views.png. Run: .venv/bin/python benchmarks/plot_randomized_views.py"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from jetbot_rt.config.sections import from_dict
from jetbot_rt.train.env import JetbotEnv

OUT = Path(__file__).resolve().parent.parent / "docs" / "images" / "randomized_views.png"
SEEDS = [0, 1, 2, 3, 4, 5, 6]


def main() -> None:
    config = from_dict({"actions": {"max_speed": 0.4}})
    fig, axes = plt.subplots(2, len(SEEDS) + 1, figsize=(2.2 * (len(SEEDS) + 1), 4.8))
    for row, size in enumerate([(224, 224), (64, 64)]):
        for col, seed in enumerate([None, *SEEDS]):
            env = JetbotEnv("forward", config, randomize=seed is not None, image_size=size)
            try:
                obs, info = env.reset(seed=seed or 0, options={"start_noise": False})
            finally:
                env.close()
            ax = axes[row, col]
            ax.imshow(obs)
            ax.set_xticks([])
            ax.set_yticks([])
            if seed is None:
                ax.set_title(f"ideal {size[0]}px", fontsize=8)
            else:
                s = info["sim_params"]
                ax.set_title(
                    f"seed {seed}: gain {s['wheel_gain'][0]:.2f}/{s['wheel_gain'][1]:.2f}\n"
                    f"pitch {s['camera_pitch_deg']:.0f} fov {s['camera_vfov_deg']:.0f} "
                    f"light {s['light_intensity']:.2f}", fontsize=6)
    fig.tight_layout()
    OUT.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(OUT, dpi=110)
    print(OUT)


if __name__ == "__main__":
    main()

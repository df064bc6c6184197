"""What a policy looks at: occlusion saliency over frames of the held-out looks and of training.

For each held-out appearance condition (benchmarks/appearance_conditions/*.toml) and a few
draws of the training randomization, two frames the policy sees (at its input size), the
task's expert driving from the episode's start: the first with the goal's bearing inside
``--bearing`` degrees, and the first nearer than ``--near`` m (where seek must stop; each
tile says the distance). Beside each, the occlusion map: a grey patch (``--patch`` pixels,
the blank ablation's grey) slides over the frame in steps of ``--stride``; each pixel gets
the mean over the patches covering it of ``|mu_left - mu_left'| + |mu_right - mu_right'|``,
the change of both wheel commands. Everything runs through onnxruntime (the runtime's
``OnnxPolicy``: any model the runtime takes, no torch). Each tile names the condition, the
commands ``mu`` and the share of the map's mass within half a patch of the frame's red pixels
(``near red``, against the share of the frame that is). The tiles' figures, with the
versions, go to benchmarks/results/saliency/OUT_STEM.json.

Run:
  .venv/bin/python benchmarks/plot_saliency.py                        # the bundled seek.onnx
  .venv/bin/python benchmarks/plot_saliency.py \\
      --policy /work/notes/runs4/seek_lens_looks/policy.onnx \\
      --config benchmarks/train_configs/seek_lens_looks.toml \\
      --out docs/images/saliency_seek_lens_looks.png

``--config`` (a TOML) lies under every condition (a condition's own keys win) and is the
training randomization the randomized tiles draw from.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from jetbot_rt.errors import UsageError

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "saliency"
IMAGES = HERE.parent / "docs" / "images"
RED_FLOOR = 0.3
"""More of the frame than this near red: the floor or a rug is red too, the share says nothing."""
GREY = 128  # the blank ablation's level (jetbot_rt.train.evaluate.BLANK_LEVEL)


def _outputs(policy: Any, images: list[np.ndarray]) -> np.ndarray:
    """``mu`` of every image, [n, 2]: one batch when the model's batch is free, else one by one."""
    batch = policy.session.get_inputs()[0].shape[0]
    tensors = [policy.prepare(image) for image in images]
    if not isinstance(batch, int) or batch <= 0:
        (mu,) = policy.session.run([policy.action_output],
                                   {policy.spec.name: np.concatenate(tensors)})
        return np.asarray(mu, dtype=np.float64).reshape(len(images), 2)
    return np.stack([
        np.asarray(policy.session.run([policy.action_output], {policy.spec.name: t})[0],
                   dtype=np.float64).reshape(2)
        for t in tensors
    ])


def occlusion_map(policy: Any, image: np.ndarray, patch: int = 8,
                  stride: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """(``mu`` of the frame, the map): the frame at the policy's input size; each pixel the mean
    over the patches covering it of the L1 change of ``mu`` when that patch is grey. Patches
    start half a patch outside the frame so the edges are covered as often as the middle."""
    if patch < 1 or stride < 1:
        raise ValueError("patch and stride must be positive")
    frame = policy.fit(image)
    height, width = frame.shape[:2]
    boxes = []
    occluded = []
    for y in range(-(patch // 2), height - patch // 2 + 1, stride):
        for x in range(-(patch // 2), width - patch // 2 + 1, stride):
            y0, y1, x0, x1 = max(y, 0), min(y + patch, height), max(x, 0), min(x + patch, width)
            if y1 <= y0 or x1 <= x0:
                continue
            grey = frame.copy()
            grey[y0:y1, x0:x1] = GREY
            boxes.append((y0, y1, x0, x1))
            occluded.append(grey)
    mus = _outputs(policy, [frame, *occluded])
    base, changes = mus[0], np.abs(mus[1:] - mus[0]).sum(axis=1)
    total = np.zeros((height, width))
    count = np.zeros((height, width))
    for (y0, y1, x0, x1), change in zip(boxes, changes, strict=True):
        total[y0:y1, x0:x1] += change
        count[y0:y1, x0:x1] += 1
    return base, total / np.maximum(count, 1)


def red_mask(frame: np.ndarray, grow: int = 0) -> np.ndarray:
    """Pixels of the goal's red (hue within 15 degrees of 0, saturated, not dark), grown by
    ``grow`` pixels every way: a patch that covers part of the block counts as on it."""
    hsv = cv2.cvtColor(frame, cv2.COLOR_RGB2HSV_FULL).astype(np.float64)
    hue = hsv[..., 0] * 360.0 / 256.0
    near = np.minimum(hue, 360.0 - hue) < 15.0
    red = near & (hsv[..., 1] > 0.45 * 255) & (hsv[..., 2] > 0.2 * 255)
    if grow > 0:
        kernel = np.ones((2 * grow + 1, 2 * grow + 1), np.uint8)
        red = cv2.dilate(red.astype(np.uint8), kernel).astype(bool)
    return red


def moments(env: Any, seed: int, expert: Any, bearing_deg: float, near: float,
            max_steps: int | None = None) -> list[tuple[np.ndarray, float]]:
    """Two (frame, distance to the goal in m) of the episode ``seed``, the task's expert
    driving: the first frame with the goal within ``bearing_deg`` of the heading, and the
    first nearer than ``near`` m (the stop, where a seek episode fails most) or, when the
    episode never comes that near, its nearest."""
    obs, info = env.reset(seed=seed)
    if "goal_xy" not in info:
        raise UsageError(f"task {env.task.name!r} has no goal to look at (no goal_xy in its info)")
    seen: list[tuple[np.ndarray, float]] = []
    nearest: tuple[np.ndarray, float] = (obs, math.inf)
    for _ in range(max_steps or env.task.episode_steps):
        x, y, yaw = (float(v) for v in info["pose"])
        gx, gy = (float(v) for v in info["goal_xy"])
        error = math.atan2(gy - y, gx - x) - yaw
        distance = math.hypot(gx - x, gy - y)
        if not seen and abs(math.degrees(math.atan2(math.sin(error), math.cos(error)))) \
                < bearing_deg:
            seen.append((obs, distance))
        if distance < nearest[1]:
            nearest = (obs, distance)
        if seen and distance < near:
            break
        obs, _, terminated, truncated, info = env.step(expert.label(info))
        if terminated or truncated:
            break
    return [*seen, nearest, nearest][:2]


def merged(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """``over`` on ``base``, section by section."""
    out = {k: dict(v) if isinstance(v, dict) else v for k, v in base.items()}
    for section, values in over.items():
        if isinstance(values, dict) and isinstance(out.get(section), dict):
            out[section].update(values)
        else:
            out[section] = values
    return out


def tiles(args: argparse.Namespace, policy: Any) -> list[tuple[str, np.ndarray]]:
    """(label, frame) for each condition and each randomized draw."""
    from jetbot_rt.config.sections import from_dict, read_toml
    from jetbot_rt.train.env import JetbotEnv
    from jetbot_rt.train.expert import task_expert

    base = read_toml(args.config) if args.config else {}
    expert = task_expert(args.task)
    size = (policy.spec.width, policy.spec.height)
    jobs: list[tuple[str, dict[str, Any], bool, int]] = []
    for path in sorted(args.conditions.glob("*.toml")):
        jobs.append((path.stem, merged(base, read_toml(path)), False, args.seed))
    for i in range(args.randomized):
        jobs.append((f"training draw {i + 1}", base, True, args.seed + 100 + i))
    if not jobs:
        raise UsageError(f"no *.toml in {args.conditions} and --randomized 0: nothing to plot")
    out = []
    for name, data, randomize, seed in jobs:
        env = JetbotEnv(args.task, from_dict(data), randomize=randomize, image_size=size,
                        model_max_speed=policy.max_speed)
        try:
            out += [(f"{name}, {distance:.2f} m", frame) for frame, distance
                    in moments(env, seed, expert, args.bearing, args.near)]
        finally:
            env.close()
        print(name, flush=True)
    return out


def plot(args: argparse.Namespace, policy: Any, frames: list[tuple[str, np.ndarray]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    per_row = 4  # two conditions a row, each in view and near
    rows = math.ceil(len(frames) / per_row)
    fig, axes = plt.subplots(rows, 2 * per_row, figsize=(2.0 * 2 * per_row, 2.35 * rows))
    axes = np.atleast_2d(axes)
    for ax in axes.flat:
        ax.set_xticks([])
        ax.set_yticks([])
        ax.axis("off")
    rows_out: list[dict[str, Any]] = []
    for i, (name, image) in enumerate(frames):
        mu, heat = occlusion_map(policy, image, args.patch, args.stride)
        frame = policy.fit(image)
        red = red_mask(frame, args.patch // 2)
        mass = heat.sum()
        on_red = heat[red].sum() / mass if mass > 0 else 0.0
        row, col = divmod(i, per_row)
        left, right = axes[row, 2 * col], axes[row, 2 * col + 1]
        left.imshow(frame)
        left.set_title(f"{name}\nmu {mu[0]:+.2f} {mu[1]:+.2f}", fontsize=7)
        right.imshow(frame)
        peak = float(heat.max())
        right.imshow(heat, cmap="inferno", alpha=0.6, vmin=0.0, vmax=peak if peak > 0 else 1.0)
        share = (f"{100 * on_red:.0f} % of the map\nnear red ({100 * red.mean():.0f} % of the px)"
                 if red.mean() < RED_FLOOR else "\n(red floor: no share)")
        right.set_title(f"peak {peak:.2f}; {share}", fontsize=7)
        rows_out.append({"tile": name, "mu": [round(float(m), 3) for m in mu],
                         "peak": round(peak, 4),
                         "near_red_share": (round(float(on_red), 3)
                                            if red.mean() < RED_FLOOR else None),
                         "red_pixel_share": round(float(red.mean()), 4)})
        print(f"{name}: mu {mu[0]:+.2f} {mu[1]:+.2f}, peak {peak:.3f}, near red "
              f"{100 * on_red:.0f} % of the map ({100 * red.mean():.1f} % of the px)",
              flush=True)
    fig.suptitle(f"{args.policy_shown}: occlusion saliency ({args.patch} px grey patch, "
                 f"stride {args.stride}, |d mu_left| + |d mu_right|, each map to its own peak)"
                 + (f"; under {args.config.name}" if args.config else ""), fontsize=9)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=100)
    from versions import stamp

    RESULTS.mkdir(parents=True, exist_ok=True)
    record = RESULTS / f"{args.out.stem}.json"
    record.write_text(json.dumps(stamp({
        "command": "python benchmarks/plot_saliency.py " + " ".join(sys.argv[1:]),
        "policy": args.policy_shown, "config": str(args.config) if args.config else None,
        "patch": args.patch, "stride": args.stride, "tiles": rows_out}), indent=2) + "\n")
    print(args.out, record)


def main() -> int:
    from jetbot_rt.config.sections import Config
    from jetbot_rt.runtime.policy import OnnxPolicy, resolve_policy_path

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policy", default=None, help="ONNX file (default: the task's bundled)")
    parser.add_argument("--task", default="seek")
    parser.add_argument("--config", type=Path, default=None,
                        help="TOML under every condition and the randomized draws' ranges")
    parser.add_argument("--conditions", type=Path, default=HERE / "appearance_conditions")
    parser.add_argument("--randomized", type=int, default=3, help="training draws to show")
    parser.add_argument("--seed", type=int, default=30000)
    parser.add_argument("--bearing", type=float, default=15.0,
                        help="degrees: the frame is taken once the goal is this near ahead")
    parser.add_argument("--near", type=float, default=0.13,
                        help="m: the second frame is taken once the goal is this near")
    parser.add_argument("--patch", type=int, default=8)
    parser.add_argument("--stride", type=int, default=2)
    parser.add_argument("--out", type=Path, default=IMAGES / "saliency_seek.png")
    args = parser.parse_args()
    try:
        if args.patch < 1 or args.stride < 1 or args.randomized < 0:
            raise UsageError("--patch and --stride must be >= 1, --randomized >= 0")
        path = resolve_policy_path(args.policy, args.task)
        policy = OnnxPolicy.load(path, Config().policy)
        args.policy_shown = "/".join(path.parts[-2:])
        plot(args, policy, tiles(args, policy))
    except UsageError as exc:
        print(f"plot_saliency: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())

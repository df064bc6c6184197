"""jetbot-train's PPO side by side with Stable-Baselines3's PPO, in one run on one machine:
the same registered env (``JetbotSeek-v0``, its domain randomization on), the same reward
shaping wrappers, the same number of env processes and the same wall-clock budget each (one
after the other, so each has the whole machine), then the same evaluation episodes
(seeds 10000 + i, deterministic actions, randomization on). Writes
benchmarks/results/vs_sb3.json and vs_sb3.md.

    pip install 'jetbot_rt[sim,train,bench]'
    python benchmarks/bench_vs_sb3.py --budget-s 600 --num-envs 2 --episodes 50

SB3 is configured only as its documentation advises for image observations: ``CnnPolicy``
(NatureCNN; images are transposed to channel-first and scaled to 0..1 by SB3 itself) with
the RL Zoo's Atari PPO hyperparameters (n_steps 128, batch 256, 4 epochs, lr 2.5e-4 and
clip 0.1 both annealed linearly, ent_coef 0.01, vf_coef 0.5), and ``VecNormalize`` for the
reward only (the Zoo's setting for PyBullet tasks). Ours runs with its task defaults.

For seek, a third row: jetbot-train's DAgger (``--algo dagger``, the way the bundled seek
policy is trained) in the same budget. It is not like for like: DAgger's expert reads the
simulator's state (robot pose, goal position) at training time, which SB3's PPO (and ours)
never sees; the student it trains sees only the camera at run time, as the PPO policies do.
``--no-dagger`` leaves that row out.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import platform
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from versions import stamp

RESULTS = Path(__file__).resolve().parent / "results"
JETBOT_TRAIN = shutil.which("jetbot-train") or str(Path(sys.executable).parent / "jetbot-train")


def train_ours(task: str, budget_s: float, num_envs: int, out: Path,
               algo: str = "ppo") -> dict[str, Any]:
    """``jetbot-train train`` stopped by Ctrl-C at the budget: it saves and exports then."""
    length = ["--timesteps", "100000000"] if algo == "ppo" else ["--iterations", "10000"]
    args = [JETBOT_TRAIN, "train", "--task", task, "--algo", algo, *length,
            "--num-envs", str(num_envs), "--out", str(out), "--no-progress"]
    start = time.perf_counter()
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        proc.wait(timeout=budget_s)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=600)
    if not (out / "policy.onnx").exists():
        raise RuntimeError(f"jetbot-train wrote no policy: {stderr[-2000:]}")
    with (out / "metrics.csv").open() as handle:
        last = list(csv.DictReader(handle))[-1]
    steps, wall = int(last["global_step"]), float(last["wall_s"])
    return {"env_steps": steps, "train_wall_s": wall,
            "env_steps_per_s": float(last.get("steps_per_s") or round(steps / wall, 1)),
            "command_wall_s": round(time.perf_counter() - start, 1)}


def sb3_env(task: str) -> Any:
    """The registered env with the trainer's shaping (``make_train_env``), as ours gets it."""
    from jetbot_rt.train.hyperparams import ppo_args
    from jetbot_rt.train.wrappers import make_train_env

    return make_train_env(task, None, ppo_args(task).shaping)


def train_sb3(task: str, budget_s: float, num_envs: int, out: Path, seed: int) -> dict[str, Any]:
    from stable_baselines3 import PPO
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import SubprocVecEnv, VecNormalize

    start = time.perf_counter()

    class StopAtBudget(BaseCallback):
        def _on_step(self) -> bool:
            return time.perf_counter() < start + budget_s

    envs = make_vec_env(partial(sb3_env, task), n_envs=num_envs, seed=seed,
                        vec_env_cls=SubprocVecEnv if num_envs > 1 else None)
    envs = VecNormalize(envs, norm_obs=False, norm_reward=True)

    def linear(initial: float) -> Any:
        return lambda progress: progress * initial

    model = PPO("CnnPolicy", envs, n_steps=128, batch_size=256, n_epochs=4,
                learning_rate=linear(2.5e-4), clip_range=linear(0.1), ent_coef=0.01,
                vf_coef=0.5, seed=seed, verbose=0, device="cpu")
    learn_start = time.perf_counter()
    model.learn(total_timesteps=100_000_000, callback=StopAtBudget())
    learn_wall = time.perf_counter() - learn_start
    model.save(out / "sb3_ppo.zip")
    envs.close()
    return {"env_steps": int(model.num_timesteps), "train_wall_s": round(learn_wall, 1),
            "env_steps_per_s": round(model.num_timesteps / learn_wall, 1),
            "command_wall_s": round(time.perf_counter() - start, 1)}


class _Sb3Policy:
    def __init__(self, path: Path) -> None:
        from stable_baselines3 import PPO

        self.model = PPO.load(path, device="cpu")

    def infer(self, image: np.ndarray) -> np.ndarray:
        action, _ = self.model.predict(image, deterministic=True)
        return np.asarray(action, dtype=np.float64)


def evaluate_sb3(path: Path, task: str, episodes: int, seed: int) -> float:
    from jetbot_rt.train.env import JetbotEnv
    from jetbot_rt.train.evaluate import run_episode

    policy = _Sb3Policy(path)
    env = JetbotEnv(task)
    try:
        return float(np.mean([run_episode(env, policy, seed + i)["success"]
                              for i in range(episodes)]))
    finally:
        env.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="seek")
    parser.add_argument("--budget-s", type=float, default=600.0, help="training wall clock each")
    parser.add_argument("--num-envs", type=int, default=len(os.sched_getaffinity(0)))
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--tag", default="", help="suffix of the result files (a host name)")
    parser.add_argument("--no-dagger", action="store_true",
                        help="leave out the DAgger row (seek only; privileged expert)")
    args = parser.parse_args()
    from jetbot_rt.train.evaluate import evaluate

    load_before = os.getloadavg()
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        ours_dir, sb3_dir = Path(tmp) / "ours", Path(tmp) / "sb3"
        sb3_dir.mkdir()
        rows["jetbot-train PPO"] = train_ours(args.task, args.budget_s, args.num_envs, ours_dir)
        rows["Stable-Baselines3 PPO"] = train_sb3(args.task, args.budget_s, args.num_envs,
                                                  sb3_dir, args.seed)
        rows["jetbot-train PPO"]["success_rate"] = evaluate(
            ours_dir / "policy.onnx", task=args.task, episodes=args.episodes,
            num_workers=args.num_envs)["success_rate"]
        if args.task == "seek" and not args.no_dagger:
            dagger_dir = Path(tmp) / "dagger"
            name = "jetbot-train DAgger (privileged expert at training time)"
            rows[name] = train_ours(args.task, args.budget_s, args.num_envs, dagger_dir,
                                    "dagger")
            rows[name]["success_rate"] = evaluate(
                dagger_dir / "policy.onnx", task=args.task, episodes=args.episodes,
                num_workers=args.num_envs)["success_rate"]
        rows["Stable-Baselines3 PPO"]["success_rate"] = evaluate_sb3(
            sb3_dir / "sb3_ppo.zip", args.task, args.episodes, 10_000)
    import stable_baselines3

    report = {
        "task": args.task, "budget_s": args.budget_s, "num_envs": args.num_envs,
        "eval_episodes": args.episodes, "eval_seeds": f"10000..{10_000 + args.episodes - 1}",
        "results": rows, "stable_baselines3": stable_baselines3.__version__,
        "cpus": len(os.sched_getaffinity(0)), "machine": platform.processor() or platform.machine(),
        "load_before": [round(x, 2) for x in load_before],
        "load_after": [round(x, 2) for x in os.getloadavg()],
        "command": "python benchmarks/bench_vs_sb3.py " + " ".join(sys.argv[1:]),
    }
    suffix = f"-{args.tag}" if args.tag else ""
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"vs_sb3{suffix}.json").write_text(json.dumps(stamp(report), indent=2) + "\n")
    lines = [f"# {args.task}: jetbot-train PPO vs Stable-Baselines3 PPO, {args.budget_s:g} s "
             f"of training each, {args.num_envs} env processes", "",
             f"`{report['command']}` ({report['cpus']} CPUs, load {report['load_before']} before, "
             f"{report['load_after']} after)", "",
             f"| trainer | env steps | env steps/s | success ({args.episodes} episodes) |",
             "| --- | --- | --- | --- |"]
    for name, row in rows.items():
        lines.append(f"| {name} | {row['env_steps']} | {row['env_steps_per_s']} | "
                     f"{row['success_rate']:.0%} |")
    (RESULTS / f"vs_sb3{suffix}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()

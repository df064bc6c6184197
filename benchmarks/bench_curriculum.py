"""Does a curriculum shorten the time to 90 %? Two arms of DAgger on seek, same seed.

    python benchmarks/bench_curriculum.py --arms-in-parallel --num-envs 6 --eval-workers 2 \\
        --budget 510 --device cuda                 # a 16-core GPU host: ~8.5 min wall
    python benchmarks/bench_curriculum.py --budget 60 --steps-per-iteration 300 \\
        --train-samples 512 --eval-episodes 10     # a smoke run (validates the script)

Arm ``none``: ``jetbot-train train --task seek --algo dagger`` at full difficulty throughout.
Arm ``curriculum``: the same command with ``--curriculum`` (default schedule: difficulty from
0, +0.25 each time 80 % of the last 40 student episodes at the current difficulty succeed).
Same seed, same options, same number of cores each (with ``--arms-in-parallel`` both at once,
each pinned to half of this process's cores; without it one after the other, each with all).

Why DAgger: the question "time to 90 %" needs an arm without a curriculum that reaches 90 %
within the budget, and PPO from pixels on seek does not (docs/TRAINING.md: 5-12 % after ~66 k
steps); DAgger does (~10 min on 2 cores). Why seek: it is the built-in task with a curriculum.

Each arm's training exports ``policy_<i>.onnx`` every ``--snapshot-every`` iterations. While it
trains, an evaluator pinned to ``--eval-workers`` of the arm's cores evaluates the newest
snapshot, again and again, at FULL difficulty (fresh envs; the curriculum never reaches them)
on the fixed episodes ``--eval-seed`` + 0 .. ``--eval-episodes`` - 1 with randomization on,
as ``jetbot-train eval`` does. A snapshot's verdict is exact for the whole set of episodes
yet stops early: it passes once ``target`` of them have succeeded, fails once too many have
failed to reach it. The first snapshot that passes ends the arm's training (Ctrl-C: it saves
and exits); then, with all the arm's cores, the snapshots between the last failed one and it
are evaluated in order, so the figure is the first snapshot at or above the target after the
last one evaluated below it. Time and steps to it are the training's own (``wall_s`` and
``global_step`` of its ``metrics.csv`` row): the evaluator runs on other cores, and its time
is not counted.

Writes ``curriculum.json`` and ``curriculum.md`` (and each arm's ``metrics.csv`` and training
log) into ``$OUT/curriculum/`` when the environment variable OUT is set, else into
``benchmarks/results/``.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import multiprocessing
import os
import platform
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from versions import cpu_model, stamp

from jetbot_rt.train.versions import git_commit

REPO = Path(__file__).resolve().parent.parent
ARMS = ("none", "curriculum")
STOP_WAIT_S = 60.0
"""How long a training stopped with Ctrl-C may take to save and exit before it is killed."""
FINAL_MARGIN_S = 10.0
"""Seconds of the budget kept for writing the results."""


# -- the evaluator ------------------------------------------------------------------------

_WORKER: dict[str, Any] = {}


def _pin(cores: list[int]) -> None:
    os.sched_setaffinity(0, cores)
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _episode(job: tuple[str, str, int]) -> bool:
    """One evaluation episode of the policy ``path`` on ``task`` from ``seed`` (a fresh env
    per worker: difficulty 1, the task's randomization); whether it succeeded."""
    from jetbot_rt.config.sections import Config
    from jetbot_rt.train.env import JetbotEnv
    from jetbot_rt.train.evaluate import load_policy, run_episode

    path, task, seed = job
    if _WORKER.get("path") != path:
        policy = load_policy(path, Config())
        key = (task, policy.spec.width, policy.spec.height, policy.max_speed)
        if _WORKER.get("key") != key:
            if "env" in _WORKER:
                _WORKER["env"].close()
            _WORKER["env"] = JetbotEnv(task, Config(), model_max_speed=policy.max_speed,
                                       image_size=(policy.spec.width, policy.spec.height))
            _WORKER["key"] = key
        _WORKER.update(path=path, policy=policy)
    return bool(run_episode(_WORKER["env"], _WORKER["policy"], seed)["success"])


class Evaluator:
    """A pool of evaluation workers pinned to ``cores``."""

    def __init__(self, cores: list[int], task: str, episodes: int, seed: int,
                 target: float) -> None:
        self.task, self.episodes, self.seed = task, episodes, seed
        self.need = math.ceil(target * episodes - 1e-9)
        """Successes that pass (90 of 100)."""
        self.workers = len(cores)
        from jetbot_rt.train.vec_env import workers_ignore_the_working_directory

        with workers_ignore_the_working_directory():  # as the trainer's own workers
            self.pool = multiprocessing.get_context("spawn").Pool(
                self.workers, initializer=_pin, initargs=(cores,))

    def verdict(self, path: Path, deadline: float) -> dict[str, Any] | None:
        """Episodes in seed order, ``workers`` at a time, until the verdict on the whole set
        is certain; None if ``deadline`` (monotonic) passes first."""
        began = time.monotonic()
        successes = failures = submitted = 0
        allowed = self.episodes - self.need  # failures that still pass
        running: list[Any] = []
        while successes < self.need and failures <= allowed:
            while len(running) < self.workers and submitted < self.episodes:
                running.append(self.pool.apply_async(
                    _episode, ((str(path), self.task, self.seed + submitted),)))
                submitted += 1
            done = [r for r in running if r.ready()]
            if not done:
                if time.monotonic() > deadline:
                    return None
                time.sleep(0.02)
                continue
            for result in done:
                running.remove(result)
                if result.get():
                    successes += 1
                else:
                    failures += 1
        return {"passed": successes >= self.need, "successes": successes,
                "failures": failures, "episodes_run": successes + failures,
                "eval_s": round(time.monotonic() - began, 1)}

    def close(self) -> None:
        self.pool.terminate()
        self.pool.join()


# -- one arm --------------------------------------------------------------------------------

@dataclass
class Arm:
    name: str
    train_cores: list[int]
    eval_cores: list[int]
    run_dir: Path
    window: float
    """Seconds this arm may take."""
    end: float
    """Monotonic time by which every arm must be done."""
    start: float = 0.0
    train_deadline: float = 0.0
    deadline: float = 0.0
    evaluations: list[dict[str, Any]] = field(default_factory=list)
    stopped_by: str = ""
    exit_code: int | None = None
    error: str = ""


def metrics_rows(path: Path) -> dict[int, dict[str, str]]:
    """The complete rows of a run's ``metrics.csv`` so far, by iteration."""
    try:
        text = path.read_text()
    except (FileNotFoundError, UnicodeDecodeError):
        return {}
    text = text[: text.rfind("\n") + 1]  # a row being appended is not one yet
    return {int(row["iteration"]): row for row in csv.DictReader(io.StringIO(text))}


def snapshots(run_dir: Path) -> list[int]:
    """Iterations with an exported policy (exports are written whole, then renamed)."""
    found = []
    for path in run_dir.glob("policy_*.onnx"):
        number = path.stem.removeprefix("policy_")
        if number.isdigit():
            found.append(int(number))
    return sorted(found)


def train_command(args: argparse.Namespace, arm: Arm) -> list[str]:
    command = [sys.executable, "-m", "jetbot_rt.train.cli", "train", "--task", args.task,
               "--algo", "dagger", "--seed", str(args.seed), "--out", str(arm.run_dir),
               "--num-envs", str(args.num_envs or len(arm.train_cores)),
               "--iterations", "100000", "--snapshots", str(args.snapshot_every),
               "--device", args.device, "--no-progress"]
    for name in ("steps_per_iteration", "train_samples"):
        if getattr(args, name) is not None:
            command += ["--" + name.replace("_", "-"), str(getattr(args, name))]
    if arm.name == "curriculum":
        command.append("--curriculum")
    return command + args.train_arg


def evaluate_snapshot(arm: Arm, evaluator: Evaluator, iteration: int,
                      deadline: float) -> dict[str, Any] | None:
    verdict = evaluator.verdict(arm.run_dir / f"policy_{iteration}.onnx", deadline)
    if verdict is None:
        return None
    row = metrics_rows(arm.run_dir / "metrics.csv").get(iteration, {})
    record = {"iteration": iteration, "global_step": int(row.get("global_step") or 0),
              "wall_s": float(row.get("wall_s") or "nan"),
              "difficulty": float(row.get("difficulty") or 1.0), **verdict}
    arm.evaluations.append(record)
    print(f"[{arm.name}] iteration {iteration} ({record['wall_s']:.0f} s of training, "
          f"{record['global_step']} steps, difficulty {record['difficulty']:g}): "
          f"{'PASS' if verdict['passed'] else 'fail'} {verdict['successes']}/"
          f"{verdict['episodes_run']} in {verdict['eval_s']} s", flush=True)
    return record


def first_pass(arm: Arm) -> tuple[dict[str, Any] | None, int]:
    """The earliest passing evaluation and the latest failing iteration before it (0: none)."""
    passed = [e for e in arm.evaluations if e["passed"]]
    if not passed:
        return None, max((e["iteration"] for e in arm.evaluations), default=0)
    best = min(passed, key=lambda e: e["iteration"])
    below = [e["iteration"] for e in arm.evaluations if e["iteration"] < best["iteration"]]
    return best, max(below, default=0)


def stop(process: subprocess.Popen) -> int:
    """Ctrl-C (the trainer saves and exits); killed if it does not within STOP_WAIT_S."""
    if process.poll() is None:
        process.send_signal(signal.SIGINT)
        try:
            process.wait(timeout=STOP_WAIT_S)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
    return process.returncode


def run_arm(args: argparse.Namespace, arm: Arm) -> None:
    """Train, evaluate the newest snapshot while it trains, stop at the first pass or the
    deadline, then refine (module docstring)."""
    arm.start = time.monotonic()
    arm.deadline = min(arm.start + arm.window, arm.end)
    arm.train_deadline = arm.deadline - args.refine_share * arm.window - STOP_WAIT_S / 4
    log_path = arm.run_dir.parent / f"{arm.name}.log"
    log = log_path.open("w")
    evaluator = Evaluator(arm.eval_cores, args.task, args.eval_episodes, args.eval_seed,
                          args.target)
    process = subprocess.Popen(train_command(args, arm), cwd=REPO, stdout=log,
                               stderr=subprocess.STDOUT)
    try:
        # pinned before it starts its env workers (they inherit it); no preexec_fn: this
        # process has threads
        os.sched_setaffinity(process.pid, arm.train_cores)
        while process.poll() is None and time.monotonic() < arm.train_deadline:
            done = {e["iteration"] for e in arm.evaluations}
            fresh = [i for i in snapshots(arm.run_dir) if i not in done]
            if not fresh:
                time.sleep(0.5)
                continue
            record = evaluate_snapshot(arm, evaluator, fresh[-1], arm.train_deadline)
            if record is not None and record["passed"]:
                arm.stopped_by = "passed"
                break
        arm.stopped_by = arm.stopped_by or ("exited" if process.poll() is not None
                                            else "budget")
        arm.exit_code = stop(process)
    finally:
        if process.poll() is None:
            process.kill()
        evaluator.close()
        log.close()
    if arm.exit_code not in (0, 130, -signal.SIGKILL):
        tail = log_path.read_text(errors="replace").strip().splitlines()[-3:]
        arm.error = f"training exited {arm.exit_code}: " + " | ".join(tail)
    refine(args, arm)


def refine(args: argparse.Namespace, arm: Arm) -> None:
    """With all the arm's cores: the snapshots between the last failing evaluation and the
    first passing one, in order; with no pass, the newest snapshots not yet evaluated."""
    evaluator = Evaluator(arm.train_cores + arm.eval_cores, args.task, args.eval_episodes,
                          args.eval_seed, args.target)
    try:
        while time.monotonic() < arm.deadline:
            best, below = first_pass(arm)
            done = {e["iteration"] for e in arm.evaluations}
            if best is not None:
                todo = [i for i in snapshots(arm.run_dir)
                        if below < i < best["iteration"] and i not in done]
            else:
                todo = [i for i in snapshots(arm.run_dir) if i > below][-1:]
            if not todo or evaluate_snapshot(arm, evaluator, todo[0], arm.deadline) is None:
                break
    finally:
        evaluator.close()


def summary(arm: Arm, args: argparse.Namespace) -> dict[str, Any]:
    best, below = first_pass(arm)
    rows = metrics_rows(arm.run_dir / "metrics.csv")
    last = rows[max(rows)] if rows else {}
    unevaluated = [i for i in snapshots(arm.run_dir)
                   if best is not None and below < i < best["iteration"]
                   and i not in {e["iteration"] for e in arm.evaluations}]
    return {
        "arm": arm.name,
        "reached": best is not None,
        "iteration": best["iteration"] if best else None,
        "wall_s": best["wall_s"] if best else None,
        "global_step": best["global_step"] if best else None,
        "difficulty_then": best["difficulty"] if best else None,
        "last_failing_iteration_before": below if best else None,
        "unevaluated_between": unevaluated,
        "trained_iterations": max(rows) if rows else 0,
        "trained_wall_s": float(last.get("wall_s") or 0.0),
        "trained_steps": int(last.get("global_step") or 0),
        "final_difficulty": float(last.get("difficulty") or 1.0),  # none: 1 throughout
        "stopped_by": arm.stopped_by,
        "train_exit_code": arm.exit_code,
        "train_cores": len(arm.train_cores),
        "eval_cores_while_training": len(arm.eval_cores),
        "evaluations": sorted(arm.evaluations, key=lambda e: e["iteration"]),
        "error": arm.error,
    }


# -- the whole benchmark ----------------------------------------------------------------------

def machine() -> dict[str, Any]:
    gpu = None
    try:
        import torch

        if torch.cuda.is_available():
            gpu = torch.cuda.get_device_name(0)
    except ImportError:
        pass
    return {"host": socket.gethostname(), "cpu": cpu_model(),
            "cores_usable": len(os.sched_getaffinity(0)), "gpu": gpu,
            "python": platform.python_version(),
            "loadavg_1min_at_start": round(os.getloadavg()[0], 2)}


def results_dir() -> Path:
    out = os.environ.get("OUT")
    return Path(out) / "curriculum" if out else REPO / "benchmarks" / "results"


def split_cores(args: argparse.Namespace) -> list[tuple[list[int], list[int]]]:
    """(training cores, evaluation cores) per arm."""
    cores = sorted(os.sched_getaffinity(0))
    shares = ([cores[: len(cores) // 2], cores[len(cores) // 2:]] if args.arms_in_parallel
              else [cores, cores])
    plan = []
    for share in shares:
        if len(share) < 2:
            raise SystemExit("bench_curriculum: error: an arm needs at least 2 cores "
                             f"(one to train, one to evaluate); it has {len(share)}")
        evaluating = min(args.eval_workers or max(1, len(share) // 4), len(share) - 1)
        plan.append((share[: len(share) - evaluating], share[len(share) - evaluating:]))
    return plan


def figure_line(arms: dict[str, dict[str, Any]]) -> str:
    none, cur = arms["none"], arms["curriculum"]
    if none["reached"] and cur["reached"]:
        ratio = cur["wall_s"] / none["wall_s"] if none["wall_s"] else float("nan")
        return (f"curriculum {cur['wall_s']:.0f} s / {cur['global_step']} steps vs none "
                f"{none['wall_s']:.0f} s / {none['global_step']} steps to the target: "
                f"{ratio:.2f}x the time")
    reached = [name for name, arm in arms.items() if arm["reached"]]
    return ("neither arm reached the target within the budget" if not reached
            else f"only {reached[0]} reached the target within the budget")


def markdown(result: dict[str, Any]) -> str:
    m, o = result["machine"], result["options"]
    mode = "in parallel" if o["arms_in_parallel"] else "one after the other"
    lines = [
        "# Curriculum vs none: time to 90 % on seek (DAgger)",
        "",
        f"`{result['command']}`",
        "",
        f"{result['date']}, commit {result['commit']}; {m['host']}: {m['cpu']}, "
        f"{m['cores_usable']} usable cores, GPU {m['gpu']}, Python {m['python']}, load "
        f"{m['loadavg_1min_at_start']} at start. Arms {mode}, "
        f"seed {o['seed']}, device {o['device']}, snapshot every {o['snapshot_every']} "
        f"iterations, evaluated at full difficulty on seeds {o['eval_seed']} .. "
        f"{o['eval_seed'] + o['eval_episodes'] - 1} (target {o['target']:.0%}).",
        "",
        f"**{result['figure']}**",
        "",
        "| arm | reached | iteration | training wall s | env steps | last below at | "
        "trained (iterations, s, steps) | final difficulty | stopped by |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for arm in result["arms"].values():
        lines.append(
            f"| {arm['arm']} | {'yes' if arm['reached'] else 'no'} | {arm['iteration']} | "
            f"{arm['wall_s']} | {arm['global_step']} | {arm['last_failing_iteration_before']} | "
            f"{arm['trained_iterations']}, {arm['trained_wall_s']:.0f}, {arm['trained_steps']} | "
            f"{arm['final_difficulty']} | {arm['stopped_by']} |")
    lines += ["", "Evaluations (iteration: successes / episodes run until the verdict was "
              "certain, PASS or fail):", ""]
    for arm in result["arms"].values():
        shown = ", ".join(f"{e['iteration']}: {e['successes']}/{e['episodes_run']} "
                          f"{'PASS' if e['passed'] else 'fail'}" for e in arm["evaluations"])
        lines.append(f"- {arm['arm']}: {shown or '(none)'}")
    lines += ["", f"Whole benchmark: {result['wall_s']:.0f} s. Method: "
              "benchmarks/bench_curriculum.py's docstring; guide: docs/CURRICULUM.md.", ""]
    return "\n".join(lines)


def parse(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="seek", help="a task with a curriculum and an expert")
    parser.add_argument("--seed", type=int, default=1, help="both arms' training seed")
    parser.add_argument("--budget", type=float, default=510.0,
                        help="seconds of wall time for the whole benchmark")
    parser.add_argument("--arms-in-parallel", action="store_true",
                        help="both arms at once, each pinned to half of the cores")
    parser.add_argument("--num-envs", type=int,
                        help="env workers of each arm's training (default: its cores)")
    parser.add_argument("--eval-workers", type=int,
                        help="cores of each arm that evaluate while it trains (default a "
                             "quarter of its share, at least 1)")
    parser.add_argument("--device", default="cpu",
                        help="where DAgger's regression runs (cpu, cuda, cuda:N, auto)")
    parser.add_argument("--snapshot-every", type=int, default=2,
                        help="iterations between exported snapshots")
    parser.add_argument("--eval-episodes", type=int, default=100)
    parser.add_argument("--eval-seed", type=int, default=10_000)
    parser.add_argument("--target", type=float, default=0.9)
    parser.add_argument("--refine-share", type=float, default=0.15,
                        help="share of each arm's time kept to evaluate skipped snapshots")
    parser.add_argument("--steps-per-iteration", type=int)
    parser.add_argument("--train-samples", type=int)
    parser.add_argument("--train-arg", action="append", default=[],
                        help="one more jetbot-train argument for both arms, repeatable: "
                             "--train-arg=--beta --train-arg=0.25")
    parser.add_argument("--work", help="directory for the runs (default: a temporary one, "
                                       "removed at the end)")
    args = parser.parse_args(argv)
    if not 0 < args.target <= 1 or args.eval_episodes < 1 or args.snapshot_every < 1 \
            or args.budget < 30:
        parser.error("need 0 < --target <= 1, --eval-episodes >= 1, --snapshot-every >= 1, "
                     "--budget >= 30")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse(argv)
    began, wall_began = time.monotonic(), time.time()
    plan = split_cores(args)
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="bench_curriculum_"))
    work.mkdir(parents=True, exist_ok=True)
    usable = args.budget - FINAL_MARGIN_S
    window = usable if args.arms_in_parallel else usable / 2
    arms = [Arm(name, train, evaluate, work / name, window, began + usable)
            for name, (train, evaluate) in zip(ARMS, plan, strict=True)]

    def guarded(arm: Arm) -> None:
        try:
            run_arm(args, arm)
        except Exception as exc:  # one arm's failure is reported, the other still runs
            arm.error = f"{type(exc).__name__}: {exc}"
            print(f"[{arm.name}] failed: {arm.error}", file=sys.stderr, flush=True)

    if args.arms_in_parallel:
        threads = [threading.Thread(target=guarded, args=(arm,)) for arm in arms]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
    else:
        for arm in arms:
            guarded(arm)
    by_name = {arm.name: summary(arm, args) for arm in arms}
    result = {
        "command": shlex.join(["python", "benchmarks/bench_curriculum.py",
                               *(sys.argv[1:] if argv is None else argv)]),
        "date": datetime.fromtimestamp(wall_began, timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "commit": git_commit(REPO),  # with -dirty: what ran
        "machine": machine(),
        "options": {k: v for k, v in vars(args).items() if k != "work"},
        "curriculum": "jetbot-train defaults: --curriculum-start 0 --curriculum-step 0.25 "
                      "--curriculum-threshold 0.8 --curriculum-window 40",
        "figure": figure_line(by_name),
        "arms": by_name,
        "wall_s": round(time.monotonic() - began, 1),
    }
    out = results_dir()
    out.mkdir(parents=True, exist_ok=True)
    (out / "curriculum.json").write_text(json.dumps(stamp(result), indent=2) + "\n")
    (out / "curriculum.md").write_text(markdown(result))
    for arm in arms:
        for source, target in ((arm.run_dir / "metrics.csv", f"curriculum_{arm.name}_metrics.csv"),
                               (work / f"{arm.name}.log", f"curriculum_{arm.name}_train.log")):
            if source.exists():
                shutil.copyfile(source, out / target)
    print(result["figure"])
    print(f"wrote {out / 'curriculum.json'} and curriculum.md in {result['wall_s']:.0f} s")
    if not args.work:
        shutil.rmtree(work, ignore_errors=True)
    return 1 if any(arm.error for arm in arms) else 0


if __name__ == "__main__":
    sys.exit(main())

"""Where PPO's time goes: one ``train()`` run, its CPU and wall time split by component.

    python benchmarks/profile_ppo.py [--steps 4096] [--num-envs 2] [--tag NAME] [--set KEY=VALUE]

The learner's process CPU time (all its threads) is split into rollout inference (the
network's forward pass without gradients), the vector env's ``step`` -- or, when the workers
sample (``sample_in_workers``), its ``call_async("collect")`` and ``call_wait()`` -- as the
learner sees it (sending actions or weights, receiving results, merging infos, the reward
normaliser: CPU only, waiting for the workers is not CPU), the update (between ``train()``'s
two ``torch.set_num_threads`` calls: GAE, the epochs, the optimizer) and the rest of the
loop (buffers, bookkeeping). The env workers' CPU comes from /proc. Every figure is for the
timed loop (from the first env step to the last update), scaled to ``--steps``; wall time
besides. On a shared machine the CPU seconds are what to compare; the wall seconds depend on
the load (reported).
Writes benchmarks/results/profile_ppo[-TAG].json.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

from versions import stamp

import jetbot_rt.train  # noqa: F401  (sets the thread wait policy before torch loads)

RESULTS = Path(__file__).resolve().parent / "results"
TICKS = os.sysconf("SC_CLK_TCK")


def _proc_cpu(pid: int) -> float:
    """User + system CPU seconds of a process so far (0 once it is gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / TICKS


class Meter:
    """CPU (this process) and wall seconds per component, with hooks patched into PPO."""

    def __init__(self) -> None:
        self.cpu: dict[str, float] = {"inference": 0.0, "env_step": 0.0, "update": 0.0}
        self.wall: dict[str, float] = {"rollout": 0.0, "update": 0.0}
        self.start: tuple[float, float] | None = None
        self.end: tuple[float, float] = (0.0, 0.0)
        self.workers: list[int] = []
        self.workers_start = 0.0
        self.workers_end = 0.0
        self._update_start: tuple[float, float] | None = None

    @staticmethod
    def now() -> tuple[float, float]:
        return time.process_time(), time.perf_counter()

    def install(self, update_threads: int) -> None:
        import torch
        from gymnasium.vector import AsyncVectorEnv
        from gymnasium.wrappers.vector import ClipReward

        from jetbot_rt.train.model import ActorCritic

        meter, heads, step = self, ActorCritic.heads, ClipReward.step
        call_async, call_wait = AsyncVectorEnv.call_async, AsyncVectorEnv.call_wait
        collecting = [False]
        set_threads = torch.set_num_threads

        def begin(env: object) -> None:
            if meter.start is None:
                meter.start = meter.now()
                meter.workers = [p.pid for p in getattr(env, "processes", [])]
                meter.workers_start = sum(map(_proc_cpu, meter.workers))

        def timed_heads(model, x):  # type: ignore[no-untyped-def]
            if torch.is_grad_enabled():
                return heads(model, x)
            c = time.process_time()
            out = heads(model, x)
            meter.cpu["inference"] += time.process_time() - c
            return out

        def timed_step(env, actions):  # type: ignore[no-untyped-def]
            begin(env.unwrapped)
            c = time.process_time()
            out = step(env, actions)
            meter.cpu["env_step"] += time.process_time() - c
            return out

        # the trainer sends "collect" with call_async and takes the rollout with call_wait
        def timed_call_async(env, name, *args, **kwargs):  # type: ignore[no-untyped-def]
            if name != "collect":
                return call_async(env, name, *args, **kwargs)
            begin(env)
            c = time.process_time()
            out = call_async(env, name, *args, **kwargs)
            meter.cpu["env_step"] += time.process_time() - c
            collecting[0] = True
            return out

        def timed_call_wait(env, *args, **kwargs):  # type: ignore[no-untyped-def]
            if not collecting[0]:
                return call_wait(env, *args, **kwargs)
            c = time.process_time()
            out = call_wait(env, *args, **kwargs)
            meter.cpu["env_step"] += time.process_time() - c
            collecting[0] = False
            return out

        def timed_threads(n: int) -> None:
            if n == update_threads and meter._update_start is None and meter.start:
                meter._update_start = meter.now()
            elif meter._update_start is not None:
                c, w = meter.now()
                meter.cpu["update"] += c - meter._update_start[0]
                meter.wall["update"] += w - meter._update_start[1]
                meter._update_start = None
                meter.end = (c, w)
                meter.workers_end = sum(map(_proc_cpu, meter.workers))
            set_threads(n)

        ActorCritic.heads = timed_heads  # type: ignore[method-assign]
        ClipReward.step = timed_step  # type: ignore[method-assign]
        AsyncVectorEnv.call_async = timed_call_async  # type: ignore[method-assign]
        AsyncVectorEnv.call_wait = timed_call_wait  # type: ignore[method-assign]
        torch.set_num_threads = timed_threads

    def report(self, steps_done: int, steps: int) -> dict:
        assert self.start is not None
        scale = steps / steps_done
        loop_cpu = self.end[0] - self.start[0]
        loop_wall = self.end[1] - self.start[1]
        cpu = {k: v * scale for k, v in self.cpu.items()}
        cpu["learner_other"] = loop_cpu * scale - sum(cpu.values())
        cpu["workers"] = (self.workers_end - self.workers_start) * scale
        return {
            "steps_measured": steps_done,
            "scaled_to_steps": steps,
            "env_steps_per_s": round(steps_done / loop_wall, 1),
            "core_s": {k: round(v, 2) for k, v in cpu.items()},
            "core_s_total": round(sum(cpu.values()), 2),
            "wall_s": {"loop": round(loop_wall * scale, 2),
                       "update": round(self.wall["update"] * scale, 2),
                       "rollout": round((loop_wall - self.wall["update"]) * scale, 2)},
        }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=4096)
    parser.add_argument("--num-envs", type=int, default=2)
    parser.add_argument("--task", default="forward")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a PPOArgs override as JSON, e.g. --set update_threads=1 "
                             "--set 'model={\"first_stride\": 2, \"first_kernel\": 5}'")
    parser.add_argument("--tag", default="")
    args = parser.parse_args()

    from jetbot_rt.train.hyperparams import ppo_args
    from jetbot_rt.train.ppo import train

    overrides = {k: json.loads(v) for k, v in (s.split("=", 1) for s in args.set)}
    with tempfile.TemporaryDirectory() as out:
        ppo = ppo_args(args.task, {"total_timesteps": args.steps, "num_envs": args.num_envs,
                                   "out": out, "progress": False, **overrides})
        meter = Meter()
        meter.install(ppo.update_threads)
        load_start = os.getloadavg()[0]
        summary = train(ppo)
    result = {
        "settings": {"task": args.task, "num_envs": args.num_envs, **overrides,
                     "model": ppo.model.to_dict(), "update_epochs": ppo.update_epochs,
                     "num_minibatches": ppo.num_minibatches,
                     "update_threads": ppo.update_threads,
                     "physics_hz": ppo.config.sim.physics_hz},
        "loadavg_1min": [round(load_start, 2), round(os.getloadavg()[0], 2)],
        **meter.report(summary["global_step"], args.steps),
    }
    name = f"profile_ppo-{args.tag}" if args.tag else "profile_ppo"
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"{name}.json").write_text(json.dumps(stamp(result), indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()

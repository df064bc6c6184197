"""``jetbot-train``: train a policy in the sim, export a checkpoint to ONNX, evaluate a policy.

Bad input (unknown task, missing or foreign checkpoint, non-positive counts, an output path
that cannot be written) is one line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from jetbot_rt.cli import OneLineParser, plain
from jetbot_rt.config import load_config
from jetbot_rt.errors import EXIT_OK, EXIT_USAGE, UsageError


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {value}")
    return value


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog="jetbot-train", description=plain(__doc__.splitlines()[0]))
    sub = parser.add_subparsers(dest="command", required=True, parser_class=OneLineParser)

    train = sub.add_parser("train", help="train a policy with PPO in the PyBullet sim",
                           description="train a policy with PPO in the PyBullet sim")
    train.add_argument("--task", default="forward", help="task name (default forward)")
    train.add_argument("--timesteps", type=_positive_int, required=True,
                       help="environment steps in total, over all envs")
    train.add_argument("--num-envs", type=_positive_int, default=os.cpu_count() or 1,
                       help="envs stepped together (default: one per core)")
    train.add_argument("--workers", type=int, default=None,
                       help="env processes: 0 runs the envs in the training process; "
                            "default one process per env")
    train.add_argument("--ray", nargs="?", const="local", metavar="ADDRESS",
                       help="env workers as Ray actors: alone, Ray on this machine; 'auto' "
                            "the cluster this machine is in; or HOST:PORT (needs the cluster "
                            "extra; docs/TRAINING.md)")
    train.add_argument("--out", required=True, help="output directory")
    train.add_argument("--config", help="TOML config (sim, actions, loop sections are used)")
    train.add_argument("--seed", type=int, default=1, help="seed of the envs and of PPO")
    train.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt")
    train.add_argument("--no-progress", action="store_true", help="no progress bar")

    export = sub.add_parser("export", help="export a checkpoint to ONNX (with a parity check)",
                            description="export a checkpoint to ONNX (with a parity check)")
    export.add_argument("--checkpoint", required=True, help="checkpoint.pt written by train")
    export.add_argument("--out", required=True, help="ONNX file to write")
    export.add_argument("--opset", type=_positive_int, default=16, help="ONNX opset")

    evaluate = sub.add_parser("eval", help="evaluate an ONNX policy deterministically (mu)",
                              description="evaluate an ONNX policy deterministically (mu)")
    evaluate.add_argument("--policy", help="ONNX file (default: the bundled policy)")
    evaluate.add_argument("--task", default="forward", help="task name")
    evaluate.add_argument("--episodes", type=_positive_int, default=100,
                          help="episodes to run")
    evaluate.add_argument("--num-envs", type=_positive_int, default=os.cpu_count() or 1,
                          help="worker processes (default: one per core)")
    evaluate.add_argument("--seed", type=int, default=10_000,
                          help="episode i starts from the pose drawn with seed + i")
    evaluate.add_argument("--config", help="TOML config")
    evaluate.add_argument("--json", action="store_true", help="one JSON object on stdout")
    evaluate.add_argument("--video", metavar="DIR",
                          help="record each episode into DIR/episode-<seed>/ as run --record "
                               "does (look at it with jetbot-rt report)")
    return parser


def _train(args: argparse.Namespace) -> int:
    from jetbot_rt.train.env import get_task
    from jetbot_rt.train.ppo import PPOArgs, train

    get_task(args.task)
    config = load_config(args.config)
    summary = train(PPOArgs(
        task=args.task, total_timesteps=args.timesteps, num_envs=args.num_envs,
        workers=args.workers, ray=args.ray, out=args.out,
        config=config, seed=args.seed, resume=args.resume, progress=not args.no_progress,
    ))
    print(f"trained {summary['global_step']} steps in {summary['wall_s']:.0f} s "
          f"({summary['steps_per_s']} steps/s); checkpoint {summary['checkpoint']}, "
          f"policy {summary['policy']}")
    return EXIT_OK


def _export(args: argparse.Namespace) -> int:
    from jetbot_rt.train.export import export_checkpoint

    out = Path(args.out)
    if out.is_dir():
        raise UsageError(f"--out {out} is a directory, expected an .onnx file path")
    error = export_checkpoint(args.checkpoint, out, opset=args.opset)
    print(f"wrote {out} (opset {args.opset}); onnxruntime vs torch max abs diff {error:.2e}")
    return EXIT_OK


def _eval(args: argparse.Namespace) -> int:
    from jetbot_rt.train.evaluate import evaluate

    # PyBullet's C library prints a banner on stdout; with --json, stdout carries only JSON.
    json_out = os.fdopen(os.dup(1), "w") if args.json else sys.stdout
    if args.json:
        sys.stdout.flush()
        os.dup2(2, 1)
    result = evaluate(
        args.policy, task=args.task, episodes=args.episodes, seed=args.seed,
        num_workers=args.num_envs, config=load_config(args.config), video_dir=args.video,
    )
    if args.json:
        json_out.write(json.dumps(result) + "\n")
        json_out.flush()
    else:
        print(f"policy {result['policy']}, task {result['task']}: "
              f"success {result['success_rate']:.0%} over {result['episodes']} episodes, "
              f"mean return {result['mean_return']:.4g}, "
              f"mean final distance {result['mean_final_distance']:.3f} m "
              f"(success: final distance < {result['success_distance']} m)")
    return EXIT_OK


COMMANDS = {"train": _train, "export": _export, "eval": _eval}


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(sys.argv[1:] if argv is None else argv)
    try:
        return COMMANDS[args.command](args)
    except UsageError as exc:
        print(f"jetbot-train {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())

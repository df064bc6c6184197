"""``jetbot-train``: train a policy in the sim, export a checkpoint to ONNX, evaluate a policy.

Bad input (unknown task, missing or foreign checkpoint, non-positive counts, an output path
that cannot be written, ``--device cuda`` without CUDA) is one line on stderr and exit code 2.
Without the ``train`` extra installed, one line naming it, exit code 2. Ctrl-C: checkpoint,
resume command, exit 130. ``--ray`` env workers lost beyond their restarts: one line, the
checkpoint written if an update had finished, exit 75.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import shlex
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from jetbot_rt.cli_parser import HelpFormatter, OneLineParser, plain
from jetbot_rt.errors import EXIT_OK, EXIT_USAGE, UsageError

if TYPE_CHECKING:
    from jetbot_rt.train.hyperparams import OptionError

TRAIN_EXTRA_MODULES = ("torch", "onnx", "gymnasium", "matplotlib", "tqdm", "pybullet")
EXIT_INTERRUPTED = 130
EXIT_WORKERS_LOST = 75
"""``--ray``: env workers lost beyond their restarts (sysexits' EX_TEMPFAIL: try again later,
with ``--resume`` when a checkpoint was written)."""
ALGOS = ("ppo", "dagger")
TASK_HELP = ("a task's name (tasks below), path/to/file.py:Class or package.module:Class "
             "(docs/TASKS.md)")


FLAG_OF = {"num_workers": "--num-envs", "ray_address": "--ray"}
"""Library parameters whose flag is not their name spelled as a flag."""


def flag(name: str) -> str:
    """The command-line flag of a trainer parameter (``model.hidden``: ``--model-hidden``)."""
    return FLAG_OF.get(name) or "--" + name.replace(".", "-").replace("_", "-")


def spelled(error: OptionError, table: dict[str, Any], args: argparse.Namespace) -> UsageError:
    """``error`` as the user wrote the parameter: its flag, or ``[train] NAME`` (``[train.model]
    NAME``) where the config's table set it and no flag did (flags given are the only
    attributes of ``args``: their default is ``SUPPRESS``)."""
    section, _, key = error.name.rpartition(".")
    given = table.get("model", {}) if section == "model" else table
    if isinstance(given, dict) and key in given and error.name not in vars(args):
        where = "[train.model]" if section == "model" else "[train]"
        return UsageError(f"{where} {key} {error.problem}")
    return UsageError(f"{flag(error.name)} {error.problem}")


def _task_list() -> str:
    from jetbot_rt.tasks.loader import describe

    return "tasks: " + describe() + "; or your own: FILE.py:Class (docs/TASKS.md)"


def default_algo(task: str) -> str:
    """dagger where the task has a privileged expert (docs/TRAINING.md, "Training seek by
    DAgger", says why), else ppo."""
    from jetbot_rt.tasks import load_task

    return "dagger" if load_task(task).expert() is not None else "ppo"


def build_parser() -> argparse.ArgumentParser:
    from jetbot_rt.train.evaluate import ABLATIONS
    from jetbot_rt.train.flags import add_ppo_arguments, positive_int

    formatter = HelpFormatter  # defaults shown, never "(default: None)"
    parser = OneLineParser(prog="jetbot-train", description=plain(__doc__.splitlines()[0]),
                           epilog=_task_list())
    sub = parser.add_subparsers(dest="command", required=True, parser_class=OneLineParser)
    cores = os.cpu_count() or 1

    train = sub.add_parser(
        "train", help="train a policy (PPO or DAgger) in the PyBullet sim",
        formatter_class=formatter,
        description="Train a camera-image policy with PPO or DAgger in the PyBullet sim. Writes "
        "checkpoint.pt, policy.onnx, metrics.csv, learning_curve.png (and TensorBoard events "
        "when tensorboard is installed) to --out. Ctrl-C saves a checkpoint and prints the "
        "command that resumes.", epilog=_task_list())
    train.add_argument("--task", default="forward", help="the task to learn: " + TASK_HELP)
    train.add_argument("--config", help="TOML file: [sim], [actions], [loop] shape the env; "
                       "a [train] table (and [train.model]) sets the options below")
    train.add_argument(
        "--algo", choices=ALGOS,
        help="ppo: reinforcement learning from the task's reward; dagger: imitation of a "
        "privileged expert that reads the sim's state (tasks with one: seek; the policy still "
        "sees only the camera). Default: dagger where the task has an expert, else ppo")
    add_ppo_arguments(train)

    export = sub.add_parser(
        "export", help="export a checkpoint to ONNX (with a parity check)",
        formatter_class=formatter,
        description="Export a training checkpoint to ONNX with jetbot_rt metadata (layout, "
        "colour order, pixel range, max_speed, task); fails (exit 2) if onnxruntime and torch "
        "disagree by 1e-4 or more.")
    export.add_argument("--checkpoint", required=True, help="checkpoint.pt from train")
    export.add_argument("--out", required=True, help="ONNX file to write")
    export.add_argument("--opset", type=positive_int, default=16, help="ONNX opset")

    ensemble = sub.add_parser(
        "ensemble", help="one ONNX policy that drives the mean of several policies' commands",
        formatter_class=formatter,
        description="Write one ONNX policy whose mu is the mean of the members' (seeds of one "
        "recipe: the same task, input and metadata contract); checked against the members "
        "before --out is replaced. Its inference costs the members' together.")
    ensemble.add_argument("policies", nargs="+", metavar="POLICY", help="ONNX files, two or more")
    ensemble.add_argument("--out", required=True, help="ONNX file to write")

    evaluate = sub.add_parser(
        "eval", help="evaluate an ONNX policy deterministically (mu)", formatter_class=formatter,
        description="Evaluate an ONNX policy on a task's seeded episodes with the runtime's "
        "frame preparation; --ablate runs the same episodes blind or with a seam opened.",
        epilog=_task_list())
    evaluate.add_argument("--policy", help="ONNX file (default: the policy bundled for --task)")
    evaluate.add_argument("--task", default="forward", help="the task: " + TASK_HELP)
    evaluate.add_argument("--episodes", type=positive_int, default=100, help="episodes")
    evaluate.add_argument("--num-envs", type=positive_int, default=cores,
                          help="worker processes (one per core)")
    evaluate.add_argument("--seed", type=int, default=10_000,
                          help="episode i uses the scene drawn with seed + i")
    evaluate.add_argument("--config", help="TOML config ([sim] conditions, [actions], [policy])")
    evaluate.add_argument(
        "--ablate", choices=ABLATIONS,
        help="blank: a constant grey image; bgr / pixel-range: frames prepared in the other "
        "colour order / pixel range than the model declares; constant-forward: mu = [1, 1], "
        "no network")
    evaluate.add_argument("--json", action="store_true", help="one JSON object on stdout")
    evaluate.add_argument("--video", metavar="DIR",
                          help="record each episode into DIR/episode-<seed>/ as run --record "
                               "does (look at it with jetbot-rt report)")
    evaluate.add_argument("--no-progress", action="store_true", help="no progress bar")
    _add_sweep_parser(sub)
    _add_finetune_parser(sub)
    return parser


def _add_finetune_parser(sub: Any) -> None:
    from jetbot_rt.train.finetune_args import FinetuneArgs
    from jetbot_rt.train.flags import positive_int

    default = FinetuneArgs([], "", "")
    finetune = sub.add_parser(
        "finetune", help="fine-tune a policy on jetbot-rt drive recordings (the person's "
        "ticks as labels), mixed with the simulator's frames", formatter_class=HelpFormatter,
        description="Fine-tune a policy on the frames of jetbot-rt drive recordings: the "
        "ticks a person drove (takeovers of a policy, or hand driving) are the labels; each "
        "batch mixes them with frames of the simulator's training randomization so that what "
        "it taught is kept. Writes OUT/policy.onnx (the runtime's contract) and "
        "OUT/finetune.json. docs/DRIVE.md.")
    finetune.add_argument("--recordings", nargs="+", required=True, metavar="DIR",
                          help="jetbot-rt drive --record directories")
    finetune.add_argument("--init", required=True,
                          help="the starting policy: an ONNX this trainer exported, or a "
                               "checkpoint.pt")
    finetune.add_argument("--out", required=True, help="output directory")
    finetune.add_argument("--task", help="the task (default: the one --init names): " + TASK_HELP)
    finetune.add_argument("--config", help="TOML: [sim]/[randomize] of the simulator's share "
                          "(default: the task's training randomization)")
    finetune.add_argument("--holdout", nargs="+", default=[], metavar="DIR",
                          help="recordings kept out of training: their action error on human "
                               "ticks, before and after, is printed")
    finetune.add_argument("--steps", type=positive_int, default=default.steps,
                          help="gradient steps")
    finetune.add_argument("--batch-size", type=positive_int, default=default.batch_size,
                          help="frames per step")
    finetune.add_argument("--learning-rate", type=float, default=default.learning_rate,
                          help="Adam's step size")
    finetune.add_argument("--sim-share", type=float, default=default.sim_share,
                          help="share of each batch from the simulator, in [0, 1)")
    finetune.add_argument("--sim-frames", type=int, default=default.sim_frames,
                          help="simulator frames collected (labelled by the task's expert)")
    finetune.add_argument("--stop-weight", type=float, default=default.stop_weight,
                          help="weight of stop labels (both wheels <= 0) in the loss")
    finetune.add_argument("--label-delay", type=int, default=default.label_delay,
                          help="ticks between a frame and the person's command that labels it "
                               "(their reaction time: 6 at 30 Hz is 0.2 s; 0: the same tick)")
    finetune.add_argument("--seed", type=int, default=default.seed, help="random seed")


def _add_sweep_parser(sub: Any) -> None:
    sweep = sub.add_parser(
        "sweep", help="train several seeds / configs across a Ray cluster, one results table",
        description="Train several seeds (and configs, e.g. randomization ranges) at once "
        "across a Ray cluster, evaluate each policy, print one table of results. Each trial "
        "is a train run with the task's PPO defaults and its config's [train] table.")
    sweep.add_argument("--task", default="forward", help="the task to learn: " + TASK_HELP)
    sweep.add_argument("--timesteps", type=int, help="env steps per trial (default: the "
                       "task's, or the config's [train] total_timesteps)")
    sweep.add_argument("--num-envs", type=int, default=2,
                       help="env processes per trial (and the CPUs it asks Ray for)")
    sweep.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3],
                       help="one trial per seed and config")
    sweep.add_argument("--config", nargs="+", metavar="TOML",
                       help="one or more TOML configs (e.g. [randomize] ranges, a [train] "
                            "table); each is trained with every seed and evaluated under "
                            "itself (default: the built-in config)")
    sweep.add_argument("--eval-episodes", type=int, default=20,
                       help="evaluation episodes per trial")
    sweep.add_argument("--ray", nargs="?", const="local", default="local", metavar="ADDRESS",
                       help="Ray cluster: 'local' (Ray on this machine), 'auto' or HOST:PORT")
    sweep.add_argument("--out", required=True, help="output directory")


def _resume_command(argv: list[str]) -> str:
    words = ["jetbot-train", *argv]
    if "--resume" not in words:
        words.append("--resume")
    return shlex.join(words)


def _train(args: argparse.Namespace, argv: list[str]) -> int:
    algo = args.algo or default_algo(args.task)  # a bad --task: refused before torch loads
    from jetbot_rt.train import dagger, ppo
    from jetbot_rt.train.flags import overrides
    from jetbot_rt.train.hyperparams import OptionError, dagger_args, ppo_args, read_config_file
    from jetbot_rt.train.ray_workers import WorkersLost
    from jetbot_rt.train.run_dir import Interrupted

    config, table = read_config_file(args.config)
    build, train = (dagger_args, dagger.train) if algo == "dagger" else (ppo_args, ppo.train)
    try:
        options = build(args.task, overrides(args, table, algo))
        options.config = config
        summary = train(options)
    except OptionError as exc:
        raise spelled(exc, table, args) from None
    except Interrupted as stop:
        summary = stop.summary
        print(f"\ninterrupted at {summary['global_step']} steps; wrote {summary['checkpoint']}, "
              f"{summary['policy']} and the learning curve. Resume with:\n"
              f"  {_resume_command(argv)}", file=sys.stderr)
        return EXIT_INTERRUPTED
    except WorkersLost as lost:
        saved = lost.summary
        tail = (f"wrote {saved['checkpoint']} at {saved['global_step']} steps; resume with: "
                f"{_resume_command(argv)}" if saved else "no update had finished, nothing saved")
        print(f"jetbot-train train: error: {lost}; {tail}", file=sys.stderr)
        return EXIT_WORKERS_LOST
    print(f"trained {summary['global_step']} steps in {summary['wall_s']:.0f} s "
          f"({summary['steps_per_s']} steps/s); checkpoint {summary['checkpoint']}, "
          f"policy {summary['policy']}")
    return EXIT_OK


def _export(args: argparse.Namespace, argv: list[str]) -> int:
    from jetbot_rt.train.export import export_checkpoint

    out = Path(args.out)
    if out.is_dir():
        raise UsageError(f"--out {out} is a directory, expected an .onnx file path")
    error = export_checkpoint(args.checkpoint, out, opset=args.opset)
    print(f"wrote {out} (opset {args.opset}); onnxruntime vs torch max abs diff {error:.2e}")
    return EXIT_OK


def _ensemble(args: argparse.Namespace, argv: list[str]) -> int:
    from jetbot_rt.train.ensemble import ensemble_policies

    written = ensemble_policies(args.policies, args.out)
    print(f"wrote {written['out']}: the mean of {len(written['members'])} policies; "
          f"max difference from the members' mean {written['parity_error']:.2e}")
    return EXIT_OK


def _eval(args: argparse.Namespace, argv: list[str]) -> int:
    from jetbot_rt.config.sections import load_config
    from jetbot_rt.train.evaluate import evaluate

    # PyBullet's C library prints a banner on stdout; with --json, stdout carries only JSON.
    json_out = os.fdopen(os.dup(1), "w") if args.json else sys.stdout
    if args.json:
        sys.stdout.flush()
        os.dup2(2, 1)
    result = evaluate(
        args.policy, task=args.task, episodes=args.episodes, seed=args.seed,
        num_workers=args.num_envs, config=load_config(args.config), ablate=args.ablate,
        video_dir=args.video,
        progress=not args.no_progress and sys.stderr.isatty(),
    )
    if args.json:
        json_out.write(json.dumps(result) + "\n")
        json_out.flush()
    else:
        ablated = f" (ablate {result['ablate']})" if result["ablate"] else ""
        print(f"policy {result['policy']}{ablated}, task {result['task']}: "
              f"success {result['success_rate']:.0%} over {result['episodes']} episodes, "
              f"mean return {result['mean_return']:.4g}"
              + (f", mean final distance {result['mean_final_distance']:.3f} m"
                 if result["mean_final_distance"] is not None else "")
              + (f" (success: {result['success_rule']})" if result["success_rule"] else ""))
    return EXIT_OK


def _sweep(args: argparse.Namespace, argv: list[str]) -> int:
    from jetbot_rt.train.sweep import markdown_table, sweep

    rows = sweep(args.task, args.out, seeds=args.seeds, configs=args.config or [None],
                 num_envs=args.num_envs, timesteps=args.timesteps,
                 eval_episodes=args.eval_episodes, ray_address=args.ray)
    print(markdown_table(rows), end="")
    return EXIT_OK


def _finetune(args: argparse.Namespace, argv: list[str]) -> int:
    from jetbot_rt.config.sections import load_config
    from jetbot_rt.train.finetune import finetune
    from jetbot_rt.train.finetune_args import FinetuneArgs

    summary = finetune(FinetuneArgs(
        recordings=args.recordings, init=args.init, out=args.out, task=args.task,
        config=load_config(args.config) if args.config else None,
        holdout=tuple(args.holdout), steps=args.steps, batch_size=args.batch_size,
        learning_rate=args.learning_rate, sim_share=args.sim_share,
        sim_frames=args.sim_frames, stop_weight=args.stop_weight,
        label_delay=args.label_delay, seed=args.seed))
    before, after = summary["action_error_before"], summary["action_error_after"]
    line = (f"fine-tuned on {summary['human_ticks']} human ticks ({summary['takeovers']} "
            f"takeovers) and {summary['sim_frames']} sim frames in {summary['wall_s']:.0f} s; "
            f"action error on the human ticks {before['train']:.3f} -> {after['train']:.3f}")
    if "holdout" in before:
        line += f", held out {before['holdout']:.3f} -> {after['holdout']:.3f}"
    print(f"{line}; policy {summary['policy']}")
    return EXIT_OK


COMMANDS = {"train": _train, "export": _export, "ensemble": _ensemble, "eval": _eval,
            "sweep": _sweep, "finetune": _finetune}


def missing_extra() -> list[str]:
    return [m for m in TRAIN_EXTRA_MODULES if importlib.util.find_spec(m) is None]


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    missing = missing_extra()
    if missing:
        print("jetbot-train: error: needs the train extra (missing "
              f"{', '.join(missing)}): pip install 'jetbot_rt[sim,train]'", file=sys.stderr)
        return EXIT_USAGE
    from jetbot_rt.train.hyperparams import OptionError

    try:
        args = build_parser().parse_args(argv)
        return COMMANDS[args.command](args, argv)
    except OptionError as exc:  # the library names the parameter; a user typed its flag
        print(f"jetbot-train {argv[0]}: error: {flag(exc.name)} {exc.problem}", file=sys.stderr)
        return EXIT_USAGE
    except UsageError as exc:
        print(f"jetbot-train {argv[0] if argv else ''}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:  # before training started (or in export/eval): nothing to save
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())

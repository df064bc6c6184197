"""``jetbot-train finetune``: learn from the robot's own frames (docs/DRIVE.md).

The labels are the person's: every tick of a ``jetbot-rt drive`` recording where a person
drove with a command in force (``driver`` human, ``human`` not null) gives its frame and that
command. With ``--policy`` those are the takeovers (HG-DAgger: the person corrects where the
policy erred, and the aggregate of corrections is the data); without, the whole hand drive
(behaviour cloning, donkeycar's workflow). Ticks where the policy drove teach nothing here
(the person accepted them, which is no label of what to do).

The network starts from ``--init``: a checkpoint of ``jetbot-train train`` or a policy ONNX
this trainer exported (its weights are read from the file's initializers and checked against
the file's own outputs). Each batch mixes the recorded frames with frames of the simulator's
training randomization (``--sim-share``, default 70 %): a few minutes of recorded frames alone
would pull the network to one room and one look, and what the simulator taught (other floors,
lights, scenes) would be forgotten; with the mix it is kept (docs/DRIVE.md measures how much).
The simulator's frames are collected first: episodes driven by the starting network or, one
in two, by the task's expert, each frame labelled by the expert (the DAgger teacher); a task
without one labels them with the starting network's own ``mu`` (distillation). The trainer's
augmentation (``dagger.jitter``: brightness, contrast, colour) and its weighted MSE (stop
labels weigh ``stop_weight``) are used on both halves.

Recordings are untrusted files: they are read by ``jetbot_rt.recording.reader`` (a regular
file, size caps, every record checked); their frames must have the network's input size.
``--holdout`` recordings give the offline score printed at the end: the mean absolute action
error on their human ticks, before and after.
"""

from __future__ import annotations

import collections
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from jetbot_rt.config import safe_file
from jetbot_rt.config.safe_file import shown
from jetbot_rt.config.sections import Config
from jetbot_rt.errors import UsageError
from jetbot_rt.teleop.hand import HUMAN
from jetbot_rt.train.dagger import Dataset, jitter
from jetbot_rt.train.decoder_log import quiet_ffmpeg
from jetbot_rt.train.finetune_args import FinetuneArgs
from jetbot_rt.train.hyperparams import ModelConfig
from jetbot_rt.train.model import ActorCritic

WEIGHT_PREFIX = "model."
PARITY_TOLERANCE = 1e-4
SUMMARY_NAME = "finetune.json"


# ---- the starting network -----------------------------------------------------------------


@dataclass
class Start:
    model: ActorCritic
    task: str
    max_speed: float
    calibrated: bool = False
    """Trained on a robot whose dead-band the runtime lifts: the fine-tuned policy is too."""


def _config_of(state: dict[str, torch.Tensor], image_size: int) -> ModelConfig:
    """The ``ModelConfig`` whose network has these weights: channels, kernel and width read
    from the shapes; the first stride is the one that gives the linear layer its input."""
    try:
        first = state["encoder.0.weight"]
        channels = tuple(int(state[f"encoder.{i}.weight"].shape[0]) for i in (0, 2, 4))
        hidden, features = (int(v) for v in state["encoder.7.weight"].shape)
    except (KeyError, ValueError, TypeError):
        raise UsageError("its weights are not those of a network jetbot-train exports "
                         "(encoder.0..7, mu_head, value_head, log_std)") from None
    kernel = int(first.shape[-1])
    for stride in (1, 2, 3, 4):
        config = ModelConfig(image_size=image_size, channels=channels,  # type: ignore[arg-type]
                             first_kernel=kernel, first_stride=stride, hidden=hidden)
        try:
            if channels[2] * config.feature_side() ** 2 == features:
                return config
        except (ValueError, ZeroDivisionError):
            continue
    raise UsageError("its layer sizes fit no network jetbot-train builds")


def start_from_onnx(path: str) -> Start:
    """The network of a policy ONNX this trainer exported, checked: the same outputs as the
    file on a few images (else it is refused: another graph around similar weights)."""
    import onnx
    from onnx import numpy_helper

    from jetbot_rt.runtime.policy import MAX_MODEL_BYTES, META_PREFIX, OnnxPolicy

    policy = OnnxPolicy.load(path)  # every check the runtime makes
    members = policy.metadata.get(META_PREFIX + "ensemble")
    if members is not None:
        raise UsageError(f"--init {shown(path)}: an ensemble ({members[:200]}): start from "
                         "one of its members (jetbot-train ensemble)")
    data = safe_file.read_bytes(path, "policy", MAX_MODEL_BYTES)
    try:
        proto = onnx.load_from_string(data)
    except Exception as exc:  # protobuf's DecodeError and friends
        raise UsageError(f"--init {shown(path)}: not an ONNX model ({exc})") from None
    state = {init.name[len(WEIGHT_PREFIX):]: torch.from_numpy(numpy_helper.to_array(init).copy())
             for init in proto.graph.initializer if init.name.startswith(WEIGHT_PREFIX)}
    spec = policy.spec
    if spec.width != spec.height or spec.layout != "NHWC" or spec.color_order != "RGB":
        raise UsageError(f"--init {shown(path)}: not a network jetbot-train exports (input "
                         f"{spec.width}x{spec.height} {spec.layout} {spec.color_order})")
    try:
        model = ActorCritic(_config_of(state, spec.width))
        model.load_state_dict(state)
    except (UsageError, RuntimeError) as exc:
        raise UsageError(f"--init {shown(path)}: {str(exc).splitlines()[0]}") from None
    model.eval()
    images = np.random.default_rng(0).integers(0, 256, (4, spec.height, spec.width, 3),
                                               dtype=np.uint8)
    with torch.no_grad():
        ours = model(torch.from_numpy(images))[0].numpy()
    theirs = np.stack([policy.infer(image) for image in images])
    error = float(np.max(np.abs(ours - theirs)))
    if not error < PARITY_TOLERANCE:
        raise UsageError(f"--init {shown(path)}: its weights in our network do not give the "
                         f"file's outputs (max diff {error:.2g}): not a network jetbot-train "
                         "exports")
    task = policy.metadata.get(META_PREFIX + "task") or "forward"
    return Start(model, task, float(policy.max_speed or 0.1), policy.calibrated)


def file_task(task: str, path: str) -> str:
    """The task a file names, unless it is code (``X.py:Class``): a policy or checkpoint is
    no one's command to run code; ``--task`` may name such a task."""
    from jetbot_rt.tasks.loader import is_code_reference

    if is_code_reference(task):
        raise UsageError(f"--init {shown(path)} names the task {task[:80]!r}, code in a file "
                         "or module; to run it, name it yourself with --task")
    return task


def load_start(path: str) -> Start:
    if Path(path).suffix.lower() == ".onnx":
        return start_from_onnx(path)
    from jetbot_rt.tasks import load_task
    from jetbot_rt.train.checkpoint import load_checkpoint
    from jetbot_rt.train.env import max_speed_of

    checkpoint = load_checkpoint(path)
    task = file_task(checkpoint.task, path)
    return Start(checkpoint.model().eval(), task, max_speed_of(Config(), load_task(task)),
                 checkpoint.calibrated)


# ---- the person's labels -----------------------------------------------------------------


@dataclass
class Labels:
    frames: np.ndarray
    labels: np.ndarray
    ticks: int
    """Ticks read (all drivers)."""
    takeovers: int


def read_labels(paths: list[str] | tuple[str, ...], image_size: int,
                label_delay: int = 0) -> Labels:
    """The frames of the human ticks with a command in force, and the commands. With
    ``label_delay`` = k, a frame's label is the command the person gave k ticks later (a
    person answers what they saw a reaction time ago); only where those k + 1 ticks follow
    each other and were all driven by hand."""
    from jetbot_rt.recording.reader import Recording

    quiet_ffmpeg()  # a truncated video: our one line, not FFmpeg's besides
    frames: list[np.ndarray] = []
    labels: list[list[float]] = []
    ticks = takeovers = 0
    for path in paths:
        seen: collections.deque[tuple[int, np.ndarray]] = collections.deque()
        recording = Recording.open(path)
        if recording.frames_path is None:
            raise UsageError(f"{shown(path)}: a telemetry file, not a recording directory "
                             "(finetune needs the frames: jetbot-rt drive --record DIR)")
        size = recording.meta.get("frame_size")
        if size != [image_size, image_size]:
            raise UsageError(f"{shown(path)}: frames of {size[0]}x{size[1]}, the network "
                             f"takes {image_size}x{image_size}")
        takeovers += sum(1 for e in recording.events if e.get("event") == "takeover")
        for record, image in recording.ticks_with_frames():
            ticks += 1
            human = record.get("human")
            tick = int(record["tick"])
            if record.get("driver") != HUMAN or human is None:
                seen.clear()
                continue
            if seen and seen[-1][0] != tick - 1:
                seen.clear()
            seen.append((tick, image))
            if len(seen) > label_delay:
                _, seen_image = seen.popleft()
                if seen_image is not None:
                    frames.append(seen_image)
                    labels.append(human)
    if not frames:
        raise UsageError(f"no human ticks with a command and a frame in {len(paths)} "
                         "recording(s) (record with jetbot-rt drive; with --policy, take "
                         "over where it errs)")
    return Labels(np.stack(frames), np.asarray(labels, dtype=np.float32), ticks, takeovers)


# ---- the simulator's share -----------------------------------------------------------------


def collect_sim(task: str, config: Config, model: ActorCritic, frames: int, max_speed: float,
                seed: int) -> Dataset:
    """``frames`` frames of the task's training randomization: the network drives (the
    expert one episode in two), the expert labels (or the network's own ``mu``)."""
    from jetbot_rt.tasks import load_task
    from jetbot_rt.train.env import JetbotEnv
    from jetbot_rt.train.expert import task_expert

    loaded = load_task(task)
    expert = task_expert(loaded) if loaded.expert() is not None else None
    env = JetbotEnv(loaded, config, model_max_speed=max_speed,
                    image_size=(model.config.image_size, model.config.image_size))
    data = Dataset(env.observation_space.shape)
    rng = np.random.default_rng(seed)
    chunk_frames: list[np.ndarray] = []
    chunk_labels: list[np.ndarray] = []
    episode = 0
    try:
        while len(data) + len(chunk_frames) < frames:
            obs, info = env.reset(seed=seed * 100_003 + episode)
            expert_drives = expert is not None and rng.random() < 0.5
            done = False
            while not done and len(data) + len(chunk_frames) < frames:
                with torch.no_grad():
                    mu = model(torch.from_numpy(obs[None]))[0][0].numpy()
                label = expert.label(info) if expert is not None else mu
                chunk_frames.append(obs)
                chunk_labels.append(np.asarray(label, dtype=np.float32))
                action = label if expert_drives else mu
                obs, _, terminated, truncated, info = env.step(np.asarray(action))
                done = terminated or truncated
            episode += 1
            data.add(np.stack(chunk_frames), np.stack(chunk_labels))
            chunk_frames, chunk_labels = [], []
    finally:
        env.close()
    return data


# ---- training -------------------------------------------------------------------------------


def _batch(frames: np.ndarray, labels: np.ndarray, count: int,
           rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    idx = rng.integers(0, len(labels), count)
    return frames[idx], labels[idx]


def regress_mixed(model: ActorCritic, person: Labels, sim: Dataset | None,
                  args: FinetuneArgs) -> list[float]:
    """``args.steps`` Adam steps of the weighted MSE of ``mu`` on batches that are
    ``sim_share`` simulator frames and the rest the person's."""
    rng = np.random.default_rng(args.seed)
    optimizer = torch.optim.Adam(model.parameters(), lr=args.learning_rate)
    sim_count = round(args.batch_size * args.sim_share) if sim is not None and len(sim) \
        else 0
    losses = []
    model.train()
    for _ in range(args.steps):
        frames, labels = _batch(person.frames, person.labels, args.batch_size - sim_count, rng)
        if sim_count:
            sim_frames, sim_labels = _batch(sim.frames, sim.labels, sim_count, rng)
            frames = np.concatenate([frames, sim_frames])
            labels = np.concatenate([labels, sim_labels])
        x = model.preprocess(torch.from_numpy(frames))
        if args.photometric_jitter > 0:
            x = jitter(x, args.photometric_jitter, rng)
        mu = model.heads(x)[0]
        target = torch.from_numpy(labels)
        weights = torch.from_numpy(np.where(np.all(labels <= 0.0, axis=1), args.stop_weight,
                                            1.0).astype(np.float32))
        loss = ((((mu - target) ** 2).sum(-1)) * weights).sum() / weights.sum()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(float(loss.item()))
    model.eval()
    return losses


def action_error(model: ActorCritic, person: Labels) -> float:
    """Mean absolute difference between the network's ``mu`` and the person's command."""
    with torch.no_grad():
        errors = [np.abs(model(torch.from_numpy(person.frames[i:i + 256]))[0].numpy()
                         - person.labels[i:i + 256]).mean()
                  * len(person.labels[i:i + 256])
                  for i in range(0, len(person.labels), 256)]
    return float(np.sum(errors) / len(person.labels))


def finetune(args: FinetuneArgs) -> dict[str, Any]:
    """Fine-tune; write ``OUT/policy.onnx`` (the runtime's contract and metadata) and
    ``OUT/finetune.json``; return the summary."""
    args.validate()
    threads = torch.get_num_threads()
    if args.torch_threads is not None:
        torch.set_num_threads(args.torch_threads)
    began = time.perf_counter()
    try:
        return _finetune(args, began)
    finally:
        torch.set_num_threads(threads)


def _finetune(args: FinetuneArgs, began: float) -> dict[str, Any]:
    from jetbot_rt.train.export import export_model
    from jetbot_rt.train.out_dir import inside, writable_directory
    from jetbot_rt.train.run_dir import POLICY_NAME, _named

    directory = writable_directory(Path(args.out))  # refused before any work
    try:
        torch.manual_seed(args.seed)
        start = load_start(args.init)
        task = args.task or file_task(start.task, args.init)
        size = start.model.config.image_size
        person = read_labels(args.recordings, size, args.label_delay)
        held = read_labels(args.holdout, size, args.label_delay) if args.holdout else None
        before = {"train": action_error(start.model, person)}
        if held is not None:
            before["holdout"] = action_error(start.model, held)
        sim = None
        if args.sim_share > 0 and args.sim_frames > 0:
            sim = collect_sim(task, args.config or Config(), start.model, args.sim_frames,
                              start.max_speed, args.seed)
        collected = time.perf_counter()
        losses = regress_mixed(start.model, person, sim, args)
        after = {"train": action_error(start.model, person)}
        if held is not None:
            after["holdout"] = action_error(start.model, held)
        out = Path(args.out)
        with _named(inside(directory), out):
            export_model(start.model, inside(directory, POLICY_NAME), task=task,
                         max_speed=start.max_speed, calibrated=start.calibrated)
        summary = {
            "policy": str(out / POLICY_NAME), "init": args.init, "task": task,
            "recordings": list(args.recordings), "holdout": list(args.holdout),
            "human_ticks": len(person.labels), "ticks_read": person.ticks,
            "takeovers": person.takeovers, "sim_frames": len(sim) if sim is not None else 0,
            "sim_share": args.sim_share, "steps": args.steps, "batch_size": args.batch_size,
            "learning_rate": args.learning_rate, "stop_weight": args.stop_weight,
            "label_delay": args.label_delay,
            "first_loss": round(losses[0], 5),
            "last_loss": round(float(np.mean(losses[-50:])), 5),
            "action_error_before": {k: round(v, 4) for k, v in before.items()},
            "action_error_after": {k: round(v, 4) for k, v in after.items()},
            "collect_s": round(collected - began, 1),
            "wall_s": round(time.perf_counter() - began, 1),
        }
        with safe_file.replaced_file(inside(directory), SUMMARY_NAME) as fd:
            os.write(fd, (json.dumps(summary, indent=1) + "\n").encode())
        return summary
    finally:
        os.close(directory)

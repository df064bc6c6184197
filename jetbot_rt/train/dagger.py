"""DAgger (Ross et al. 2011): train the camera policy by imitating a privileged teacher.

The teacher (``expert.py``) reads the simulator's state; the student is the network PPO
trains (``model.ActorCritic``, the same preprocessing and ONNX export), and sees only the
camera. Iteration 0 lets the teacher drive (with action noise, for states off its own path);
every later one lets the student drive (the teacher drives a ``beta`` share of the episodes,
``beta`` halving each iteration) and labels every frame the student saw with the teacher's
action. The frames are aggregated (uint8) and the student's ``mu`` is regressed onto the
labels (MSE, Adam) for a few epochs. A training-time privilege only: the exported policy
needs nothing but the image. docs/TRAINING.md ("Training seek by DAgger") says why.
"""

from __future__ import annotations

import contextlib
import time
from typing import Any

import numpy as np
import torch
from gymnasium.vector import VectorEnv
from tqdm import tqdm

from jetbot_rt.config.sections import Config
from jetbot_rt.tasks import load_task
from jetbot_rt.train.curriculum import Schedule, curve, metric_fields, send
from jetbot_rt.train.dagger_sampler import LabelSampler
from jetbot_rt.train.device import resolve_device
from jetbot_rt.train.env import max_speed_of
from jetbot_rt.train.expert import task_expert
from jetbot_rt.train.hyperparams import DAggerArgs, ModelConfig
from jetbot_rt.train.model import ActorCritic
from jetbot_rt.train.run_dir import Interrupted, Panel, Progress, RunDirectory, starting_model
from jetbot_rt.train.run_end import close_workers, duplicates_ignored, interrupt_noted
from jetbot_rt.train.vec_env import EnvSpec, close_vector_env, make_vector_env
from jetbot_rt.train.wrappers import Shaping

METRIC_FIELDS = ("iteration", "global_step", "wall_s", "collect_s", "regress_s", "dataset",
                 "beta", "episodes", "success_rate", "expert_success_rate", "loss")
NO_SHAPING = Shaping("none")
OUTCOME_INFO = ("is_success",)
"""The info keys DAgger reads besides the expert's inputs (its ``reads``)."""
EXPERT_SETTINGS = ("stop_distance", "min_forward", "search_bearing_deg", "search_left",
                   "search_right", "backoff_distance")
"""The DAgger options that tune an expert that has fields of these names (the goal tasks')."""


def expert_settings(options: DAggerArgs) -> dict[str, Any]:
    """The expert options given (not None), to replace the fields of those names in the
    task's expert: an option left alone keeps a task expert's own value. Before 2026-12-07
    each one had the goal expert's default and was always passed, so avoid's and follow's
    experts (min_forward 0.8 then, 0.75 since) labelled at the goal expert's 0.75."""
    return {name: getattr(options, name) for name in EXPERT_SETTINGS
            if getattr(options, name) is not None}


class Dataset:
    """The aggregated frames (uint8, as rendered), the expert's labels and whether the
    expert's rule was symmetric at each (``Expert.symmetric``), growing.

    Stored in buffers that double when full, so adding an iteration's frames copies only
    those (concatenating re-copied the whole aggregate every iteration: seconds per
    iteration late in a run). ``frames`` and ``labels`` are views of the filled part."""

    def __init__(self, shape: tuple[int, ...]) -> None:
        self._frames = np.zeros((0, *shape), dtype=np.uint8)
        self._labels = np.zeros((0, 2), dtype=np.float32)
        self._symmetric = np.zeros(0, dtype=bool)
        self._size = 0

    @property
    def frames(self) -> np.ndarray:
        return self._frames[:self._size]

    @property
    def labels(self) -> np.ndarray:
        return self._labels[:self._size]

    @property
    def symmetric(self) -> np.ndarray:
        return self._symmetric[:self._size]

    def add(self, frames: np.ndarray, labels: np.ndarray,
            symmetric: np.ndarray | None = None) -> None:
        """``symmetric``: a bool per frame (None: none is)."""
        count = len(frames)
        if not count:
            return
        needed = self._size + count
        if needed > len(self._frames):
            capacity = max(needed, 2 * len(self._frames))
            grown = np.empty((capacity, *self._frames.shape[1:]), dtype=np.uint8)
            grown[:self._size] = self.frames
            grown_labels = np.empty((capacity, 2), dtype=np.float32)
            grown_labels[:self._size] = self.labels
            grown_symmetric = np.zeros(capacity, dtype=bool)
            grown_symmetric[:self._size] = self.symmetric
            self._frames, self._labels = grown, grown_labels
            self._symmetric = grown_symmetric
        self._frames[self._size:needed] = frames
        self._labels[self._size:needed] = labels
        self._symmetric[self._size:needed] = False if symmetric is None else symmetric
        self._size = needed

    def __len__(self) -> int:
        return self._size


def jitter(x: torch.Tensor, amount: float, rng: np.random.Generator) -> torch.Tensor:
    """``x`` (preprocessed, 0..1) with per-frame brightness, contrast (about the frame's mean)
    and colour-channel gains drawn from 1 +- ``amount`` (channels 1 +- ``amount`` / 2)."""
    n = x.shape[0]

    def factors(size: tuple[int, ...], spread: float) -> torch.Tensor:
        return torch.from_numpy(rng.uniform(1 - spread, 1 + spread, size).astype(np.float32)
                                ).to(x.device)

    brightness, contrast = factors((n, 1, 1, 1), amount), factors((n, 1, 1, 1), amount)
    channels = factors((n, 3, 1, 1), amount / 2)
    mean = x.mean(dim=(1, 2, 3), keepdim=True)
    return (((x - mean) * contrast + mean) * brightness * channels).clamp(0.0, 1.0)


def label_weights(labels: np.ndarray, args: DAggerArgs) -> np.ndarray:
    """Each frame's loss weight from its ``[N, 2]`` label: ``stop_weight`` for a stop or a
    back-off (both wheels <= 0), ``turn_weight`` for a turn on the spot (one wheel backwards,
    the other forwards), else 1."""
    stop = np.all(labels <= 0.0, axis=1)
    spin = (labels.min(axis=1) < 0.0) & (labels.max(axis=1) > 0.0)
    return np.where(stop, args.stop_weight,
                    np.where(spin, args.turn_weight, 1.0)).astype(np.float32)


def mirror(x: torch.Tensor, labels: torch.Tensor, flip: np.ndarray
           ) -> tuple[torch.Tensor, torch.Tensor]:
    """``x`` (NCHW) and ``labels`` (``[N, 2]``, left and right) with the rows where ``flip``
    is true seen in a mirror: the image's columns reversed, the wheels swapped."""
    if not flip.any():
        return x, labels
    rows = torch.from_numpy(np.flatnonzero(flip)).to(x.device)
    x, labels = x.clone(), labels.clone()
    x[rows] = x[rows].flip(-1)
    labels[rows] = labels[rows].flip(-1)
    return x, labels


def regress(model: ActorCritic, optimizer: torch.optim.Optimizer, data: Dataset,
            args: DAggerArgs, rng: np.random.Generator) -> float:
    """Weighted MSE of ``mu`` onto the labels over ``args.train_samples`` frames; the mean
    loss. With ``args.mirror`` each frame the expert was symmetric on is seen in a mirror
    with that probability (``mirror``)."""
    model.train()
    losses: list[float] = []
    device = next(model.parameters()).device
    weights = torch.from_numpy(label_weights(data.labels, args)).to(device)
    labels = torch.from_numpy(data.labels).to(device)
    passes = -(-args.train_samples // max(len(data), 1))
    order = np.concatenate([rng.permutation(len(data)) for _ in range(passes)])
    for begin in range(0, args.train_samples, args.batch_size):
        idx = np.sort(order[begin:min(begin + args.batch_size, args.train_samples)])
        x = model.preprocess(torch.from_numpy(data.frames[idx]).to(device))
        if args.photometric_jitter > 0:
            x = jitter(x, args.photometric_jitter, rng)
        rows = torch.from_numpy(idx).to(device)
        targets = labels[rows]
        if args.mirror > 0:
            flip = data.symmetric[idx] & (rng.random(len(idx)) < args.mirror)
            x, targets = mirror(x, targets, flip)
        mu = model.heads(x)[0]
        error = ((mu - targets) ** 2).sum(-1)
        loss = (error * weights[rows]).sum() / weights[rows].sum()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    model.eval()
    return float(np.mean(losses)) if losses else float("nan")


def collect(envs: VectorEnv, model: ActorCritic, expert: Any, data: Dataset,
            args: DAggerArgs, iteration: int) -> dict[str, Any]:
    """Roll out one iteration in the env workers (``dagger_sampler``); add every frame of
    their finished episodes with its label."""
    beta = 1.0 if iteration == 0 else args.beta * 0.5 ** (iteration - 1)
    n = envs.num_envs
    # numpy, not tensors (see rollout.WorkerRollouts): plain bytes through the pipes
    weights = {name: w.detach().cpu().numpy().copy() for name, w in model.state_dict().items()}
    results = envs.unwrapped.call(
        "collect_labelled", weights, -(-args.steps_per_iteration // n),
        (args.seed, iteration), beta, args.expert_noise, expert, args.expert_sees)
    outcomes: dict[bool, list[float]] = {True: [], False: []}
    steps = 0
    for result in results:
        data.add(result["frames"], result["labels"], result["symmetric"])
        steps += len(result["labels"])
        for by_expert, success in result["outcomes"]:
            outcomes[by_expert].append(float(success))
    student, teacher = outcomes[False], outcomes[True]
    return {"beta": round(beta, 4), "episodes": len(student) + len(teacher), "steps": steps,
            "success_rate": round(float(np.mean(student)), 3) if student else "",
            "expert_success_rate": round(float(np.mean(teacher)), 3) if teacher else "",
            "student_successes": student}


def learning_rate_at(args: DAggerArgs, iteration: int) -> float:
    """The step size of the regression after rollout ``iteration`` (0-based)."""
    if args.final_learning_rate is None or args.iterations <= 1:
        return args.learning_rate
    ratio = args.final_learning_rate / args.learning_rate
    return args.learning_rate * ratio ** (min(iteration, args.iterations - 1)
                                          / (args.iterations - 1))


def labelling_spec(task: str, config: Config, model: ModelConfig) -> EnvSpec:
    """Envs driven by a ``LabelSampler`` each, with the task's reward as is (DAgger reads only
    the expert's inputs and the outcome)."""
    keep = (*task_expert(task).reads, *OUTCOME_INFO)
    return EnvSpec(task, config, NO_SHAPING, model.image_size, keep=keep,
                   sampler=LabelSampler, model=model)


CURVE = (Panel("success_rate", "success rate (rollouts)", ylim=(-0.05, 1.05), style="o-",
               color="tab:green", label="student drives"),
         Panel("loss", "imitation loss (MSE)", scale=("log", {}), style="o-"))


class _Run:
    """One DAgger run's state between its iterations."""

    def __init__(self, options: DAggerArgs) -> None:
        options.validate()
        self.options = options
        self.run = RunDirectory(options.out, metric_fields(METRIC_FIELDS, options))
        saved = self.run.prepare(options.resume)
        torch.manual_seed(options.seed)
        model, resumed = starting_model(options, saved, "dagger")
        model = model.to(resolve_device(options.device))
        self.optimizer = torch.optim.Adam(model.parameters(), lr=options.learning_rate)
        self.progress = Progress()
        if resumed is not None:
            resumed.load_optimizer(self.optimizer)
            self.progress = Progress(resumed.global_step, resumed.update, resumed.wall_s,
                                     start_step=resumed.global_step)
        self.model = model.eval()
        self.rng = np.random.default_rng(options.seed + self.progress.update)
        self.max_speed = max_speed_of(options.config, load_task(options.task))
        self.expert = task_expert(options.task, expert_settings(options))
        self.schedule = Schedule.of(options, self.run, resumed is not None, self.progress.update)
        self.envs: VectorEnv | None = None

    def start_envs(self) -> VectorEnv:
        """The env workers, at the curriculum's difficulty if there is one."""
        self.envs = make_vector_env(labelling_spec(self.options.task, self.options.config,
                                                   self.model.config),
                                    self.options.num_envs, self.options.workers)
        if self.schedule is not None:
            send(self.envs, self.schedule.difficulty)
        return self.envs

    def iteration(self, data: Dataset) -> dict[str, Any]:
        """Collect an iteration's episodes in the workers, regress on the aggregate; the
        metrics row."""
        options, progress = self.options, self.progress
        assert self.envs is not None
        torch.set_num_threads(1)
        began = time.perf_counter()
        row = collect(self.envs, self.model, self.expert, data, options, progress.update)
        steps, student = row.pop("steps"), row.pop("student_successes")
        torch.set_num_threads(options.torch_threads)
        for group in self.optimizer.param_groups:
            group["lr"] = learning_rate_at(options, progress.update)
        collected = time.perf_counter()
        loss = regress(self.model, self.optimizer, data, options, self.rng)
        progress.update, progress.global_step = progress.update + 1, progress.global_step + steps
        row.update(iteration=progress.update, global_step=progress.global_step,
                   dataset=len(data), loss=round(loss, 5), collect_s=round(collected - began, 1),
                   regress_s=round(time.perf_counter() - collected, 1),
                   wall_s=round(progress.wall_s(), 1))
        if self.schedule is not None:
            self.schedule.after(row, student, self.envs)
        self.run.append_metrics(row)
        if options.snapshots and progress.update % options.snapshots == 0:
            self.run.export_policy(self.model.eval(), options.task, self.max_speed,
                                   options.config, name=f"policy_{progress.update}.onnx")
        return row

    def save(self) -> None:
        self.run.save_checkpoint(algo="dagger", options=self.options, model=self.model,
                                 optimizer=self.optimizer, progress=self.progress,
                                 max_speed=self.max_speed)


def train(options: DAggerArgs) -> dict[str, Any]:
    """Run DAgger; writes checkpoint, ONNX, metrics and curve to ``options.out``; returns a
    summary. Ctrl-C: writes them as they are and raises ``Interrupted``."""
    run = _Run(options)
    try:
        return _train(run, options)
    finally:
        run.run.close()


def _train(run: _Run, options: DAggerArgs) -> dict[str, Any]:
    with contextlib.ExitStack() as after_interrupt:  # a Ctrl-C's copy: ignored till the export
        return _train_until_done(run, options, after_interrupt)


def _train_until_done(run: _Run, options: DAggerArgs, after_interrupt: contextlib.ExitStack
                      ) -> dict[str, Any]:
    progress = run.progress
    # Counted in iterations: an iteration collects whole episodes, so its env steps overshoot
    # steps_per_iteration (a bar of env steps ended at 130 720 of 120 000 on seek).
    bar = tqdm(total=options.iterations, initial=min(progress.update, options.iterations),
               disable=not options.progress, unit="it", dynamic_ncols=True)
    interrupted = False
    try:  # from the workers' start on, Ctrl-C saves and prints the --resume command
        data = Dataset(run.start_envs().single_observation_space.shape)
        while progress.update < options.iterations:
            row = run.iteration(data)
            bar.update(1)
            bar.set_postfix(steps=progress.global_step, succ=row["success_rate"],
                            loss=row["loss"], refresh=False)
            run.save()
    except KeyboardInterrupt:
        interrupted = True
        after_interrupt.enter_context(duplicates_ignored())
        run.save()
    finally:
        if run.envs is not None:
            envs = run.envs
            interrupted = close_workers(lambda now: close_vector_env(envs, now), interrupted)
        bar.close()
    after_interrupt.close()  # from here interrupt_noted notes a copy (and a second raises)
    with interrupt_noted() as noted:
        run.run.export_policy(run.model.eval(), options.task, run.max_speed, options.config)
        run.run.plot_curve("jetbot-train DAgger learning curve", curve(CURVE, run.schedule))
    wall = progress.wall_s()
    summary = run.run.summary(progress, round(progress.global_step / max(wall, 1e-9), 1))
    if interrupted or noted():
        raise Interrupted(summary)
    return summary

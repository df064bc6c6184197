"""The trainers' hyperparameters, torch-free: ``PPOArgs`` (with ``TASK_DEFAULTS``),
``DAggerArgs`` and the network's ``ModelConfig``; ``OptionError`` names one out of range.

``jetbot-train``'s flags are built from these dataclasses (``flags.py``), so ``--help``, a
refused flag and ``eval`` of an ONNX policy never import torch.
"""

from __future__ import annotations

import math
import os
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any

from jetbot_rt.config.sections import Config, from_dict, read_toml
from jetbot_rt.errors import UsageError
from jetbot_rt.tasks import BUILTIN, load_task
from jetbot_rt.train.env import POLICY_IMAGE_SIZE
from jetbot_rt.train.wrappers import REWARD_TRANSFORMS, Shaping

CRITICS = ("image", "state")
"""``--critic``: what PPO's value function reads (``CriticConfig``, docs/TRAINING.md)."""
MAX_CRITIC_STATE = 4096
"""Values a task's privileged critic state may have (the built-ins have 13-20)."""
EXPERT_SEES = ("frame", "now")
"""``--expert-sees``: the state DAgger's expert labels (``dagger_sampler.FrameState``)."""

LEGACY_IMAGE_SIZE, LEGACY_POOL = 224, 4
"""What a model config without ``image_size`` means: networks exported with a 224-pixel input
that they pooled by 4 (``scripts/forward_to_56.py`` converts one)."""
MAX_IMAGE_SIZE = 1024
"""The largest input side the trainer renders: the env draws every frame at this size, and
1024 already costs ~300x the default 56's pixels a step."""
MAX_CHANNELS = 1024
MAX_HIDDEN = 65_536
SIGNED = ("seed", "workers", "ray_max_restarts", "snapshots")
"""Integer options that may be zero or negative (each checked where it is defined); every
other one must be > 0."""
INIT_RANGES = {"init_log_std": (-20.0, 2.0), "init_mu": (-10.0, 10.0)}
"""Beyond these the first rollouts' actions are constant (std e^-20) or noise (std e^2 = 7
times the action range); ``mu`` beyond 10 is clamped to 1 for many updates."""
MAX_PARAMETERS = 8_000_000
"""A network larger than this is refused (the default has 82 k-200 k): its checkpoint, with
Adam's two moments, stays under ``checkpoint.MAX_CHECKPOINT_BYTES``, so every checkpoint the
trainer writes it can read back."""


class OptionError(UsageError):
    """A trainer parameter of the wrong type or out of its range. ``name`` is the parameter
    (``model.hidden`` for the network's), ``problem`` what is wrong; the command line says
    it with the flag's name, a checkpoint's reader with the file's."""

    def __init__(self, name: str, problem: str) -> None:
        super().__init__(f"{name} {problem}")
        self.name = name
        self.problem = problem



@dataclass(frozen=True)
class ModelConfig:
    image_size: int = POLICY_IMAGE_SIZE
    """Side of the square input image (the env renders at this size, the ONNX input has it)."""
    pool: int = 1
    """Area-pooling factor applied to the input before the first convolution (divides
    ``image_size``)."""
    channels: tuple[int, int, int] = (16, 32, 32)
    """Output channels of the three convolutions."""
    first_kernel: int = 5
    """Kernel side of the first convolution (padded by ``(first_kernel - first_stride + 1)
    // 2``; the other two are 3x3, stride 2, padded by 1)."""
    first_stride: int = 2
    """Stride of the first convolution. 2: 28x28 features from a 56x56 image; 4 (with a 6x6
    kernel, forward's PPO default): 14x14, and the whole network costs about a quarter of the
    CPU per frame to train (docs/TRAINING.md, "Speed")."""
    hidden: int = 128
    """Width of the fully connected layer shared by the actor and critic heads."""
    init_log_std: float = -1.0
    """Initial log standard deviation of the action distribution (std 0.37: the task needs
    small, smooth steering corrections, not wide exploration)."""
    init_mu: float = 1.0
    """Action prior: the initial ``mu`` of both wheels (the head's bias; its weights start
    near zero). 1.0 drives straight ahead at full command from the first rollout, so early
    episodes already reach the block and PPO only has to learn the steering."""

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: Any) -> ModelConfig:
        """A config as ``to_dict`` wrote it (or a ``[train.model]`` table); ``OptionError``
        names the first bad key. Without ``image_size``: the legacy 224-pixel input."""
        if not isinstance(data, dict):
            raise OptionError("model", f"must be a table of network options, got "
                                       f"{type(data).__name__}")
        known = {f.name for f in fields(cls)}
        unknown = sorted(str(key) for key in data if key not in known)
        if unknown:
            raise UsageError(f"unknown model option(s) {', '.join(unknown)} "
                             f"(known: {', '.join(sorted(known))})")
        if "image_size" not in data:
            data = {**data, "image_size": LEGACY_IMAGE_SIZE, "pool": data.get("pool", LEGACY_POOL)}
        if "channels" in data:
            if not isinstance(data["channels"], (list, tuple)):
                raise OptionError("model.channels", "must be three integers")
            data = {**data, "channels": tuple(data["channels"])}
        return cls(**data)

    def __post_init__(self) -> None:
        for name in ("image_size", "pool", "first_kernel", "first_stride", "hidden"):
            _check_int(f"model.{name}", getattr(self, name))
        if not 8 <= self.image_size <= MAX_IMAGE_SIZE:
            raise OptionError("model.image_size", f"must be 8 .. {MAX_IMAGE_SIZE}, got "
                                                  f"{self.image_size}")
        if not 1 <= self.pool <= self.image_size or self.image_size % self.pool:
            raise OptionError("model.pool", f"must divide image_size {self.image_size}, got "
                                            f"{self.pool}")
        if (not isinstance(self.channels, tuple) or len(self.channels) != 3
                or not all(_is_int(c) and 1 <= c <= MAX_CHANNELS for c in self.channels)):
            raise OptionError("model.channels", f"must be three integers 1 .. {MAX_CHANNELS}, "
                                                f"got {value_text(self.channels)}")
        side = self.image_size // self.pool
        if not 1 <= self.first_kernel <= side:
            raise OptionError("model.first_kernel", f"must be 1 .. image_size / pool ({side}), "
                                                    f"got {self.first_kernel}")
        if not 1 <= self.first_stride <= self.first_kernel:
            raise OptionError("model.first_stride", f"must be 1 .. first_kernel "
                                                    f"({self.first_kernel}), got "
                                                    f"{self.first_stride}")
        if not 1 <= self.hidden <= MAX_HIDDEN:
            raise OptionError("model.hidden", f"must be 1 .. {MAX_HIDDEN}, got {self.hidden}")
        for name, (low, high) in INIT_RANGES.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or \
                    not low <= value <= high:
                raise OptionError(f"model.{name}", f"must be a number in [{low:g}, {high:g}], "
                                                   f"got {value_text(value)}")
        if self.parameter_count() > MAX_PARAMETERS:
            raise OptionError("model", f"has {self.parameter_count():,} parameters, more than "
                                       f"the {MAX_PARAMETERS:,} a checkpoint may hold")

    def first_padding(self) -> int:
        return (self.first_kernel - self.first_stride + 1) // 2

    def feature_side(self) -> int:
        """Side of the last convolution's feature map."""
        side = (self.image_size // self.pool + 2 * self.first_padding() - self.first_kernel
                ) // self.first_stride + 1
        for _ in range(2):
            side = (side + 1) // 2  # stride 2 with "same" padding
        return side

    def parameter_count(self) -> int:
        """The network's parameters (``model.ActorCritic``), counted without building it."""
        c1, c2, c3 = self.channels
        k, side, hidden = self.first_kernel, self.feature_side(), self.hidden
        convolutions = (3 * k * k + 1) * c1 + (9 * c1 + 1) * c2 + (9 * c2 + 1) * c3
        heads = (hidden + 1) * 2 + (hidden + 1) * 1 + 2  # mu, value, log_std
        return convolutions + (c3 * side * side + 1) * hidden + heads


@dataclass(frozen=True)
class CriticConfig:
    """An asymmetric critic (PPO's ``--critic state``; Pinto et al. 2018, "Asymmetric Actor
    Critic for Image-Based Robot Learning"): the value function is an MLP on the task's
    privileged simulator state (``Task.critic_state``), ``state_size`` values -> ``hidden``
    -> ``hidden`` -> 1, tanh between (cleanrl's critic for state observations). It reads the
    state alone, not the image features beside it: the state holds what the value depends
    on, and the value loss then never reaches the actor's encoder, which learns from the
    policy loss alone -- the actor is exactly the network the robot runs, trained for
    nothing else. The critic is a training-time part: the exported ONNX is the actor."""

    state_size: int
    """Width of the privileged state (``len(Task.critic_state_names)``)."""
    hidden: int = 64
    """Width of the critic's two hidden layers."""
    predicts_state: bool = False
    """Whether the actor also has ``state_head`` (PPO's ``--predict-state``): a linear map
    from its image features to this state, trained to predict it and never exported."""

    def __post_init__(self) -> None:
        _check_int("critic.state_size", self.state_size)
        _check_int("critic.hidden", self.hidden)
        if not isinstance(self.predicts_state, bool):
            raise OptionError("critic.predicts_state",
                              f"must be true or false, got {value_text(self.predicts_state)}")
        if not 1 <= self.state_size <= MAX_CRITIC_STATE:
            raise OptionError("critic.state_size", f"must be 1 .. {MAX_CRITIC_STATE}, got "
                                                   f"{self.state_size}")
        if not 1 <= self.hidden <= MAX_HIDDEN:
            raise OptionError("critic.hidden", f"must be 1 .. {MAX_HIDDEN}, got {self.hidden}")
        if self.parameter_count() > MAX_PARAMETERS:
            raise OptionError("critic", f"has {self.parameter_count():,} parameters, more than "
                                        f"the {MAX_PARAMETERS:,} a checkpoint may hold")

    def parameter_count(self, model: ModelConfig | None = None) -> int:
        """The critic's parameters, with the state head's on ``model``'s features when it
        has one and ``model`` is given."""
        head = (model.hidden + 1) * self.state_size if model and self.predicts_state else 0
        return (self.state_size + 1) * self.hidden + (self.hidden + 1) * self.hidden + \
            self.hidden + 1 + head

    def to_dict(self) -> dict:
        data = asdict(self)
        if not self.predicts_state:  # as checkpoints before --predict-state have it
            del data["predicts_state"]
        return data

    @classmethod
    def from_dict(cls, data: Any) -> CriticConfig:
        """A config as ``to_dict`` wrote it; ``OptionError`` names the first bad key."""
        if not isinstance(data, dict) or \
                set(data) - {"predicts_state"} != {"state_size", "hidden"}:
            raise OptionError("critic", f"must be a dict of state_size, hidden and optionally "
                                        f"predicts_state, got {value_text(data)}")
        return cls(data["state_size"], data["hidden"], data.get("predicts_state", False))


def value_text(value: Any) -> str:
    """A value as an error message shows it: a scalar's repr (cut to 40 characters), else
    its type (a tensor's repr could be pages long)."""
    scalars = (bool, int, float, str, type(None))
    flat = isinstance(value, (tuple, list)) and len(value) <= 8 and \
        all(isinstance(v, scalars) for v in value)
    if not (flat or isinstance(value, scalars)):
        return type(value).__name__
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _check_int(name: str, value: Any) -> None:
    if not _is_int(value):
        raise OptionError(name, f"must be an integer, got {value_text(value)}")


def usable_cores() -> int:
    """Cores this process may run on (``taskset``, cgroup cpusets), else the CPU count."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


@dataclass
class CurriculumOptions:
    """The curriculum's options, PPO's and DAgger's alike (docs/CURRICULUM.md)."""

    curriculum: bool = False
    """Train on easy scenes first: start at --curriculum-start difficulty and raise it by
    --curriculum-step each time --curriculum-threshold of the last --curriculum-window
    episodes at that difficulty succeed (DAgger: the student's episodes), up to 1, the task
    as evaluated; metrics.csv gains a difficulty column. For tasks whose scene reads
    Task.difficulty (seek). Off: difficulty 1 throughout."""
    curriculum_start: float = 0.0
    """The first difficulty, 0 (easiest) .. 1."""
    curriculum_threshold: float = 0.8
    """Success rate over the window that raises the difficulty, 0 .. 1."""
    curriculum_window: int = 40
    """Episodes finished at the current difficulty that the success rate is taken over
    (counted afresh after each raise)."""
    curriculum_step: float = 0.25
    """How much one raise adds to the difficulty, 0 .. 1."""

    def validate_curriculum(self) -> None:
        """``OptionError`` for a curriculum option out of range; ``UsageError`` for
        ``curriculum`` on a task whose scene does not read the difficulty."""
        for name, low_open in (("curriculum_start", False), ("curriculum_threshold", True),
                               ("curriculum_step", True)):
            value = getattr(self, name)
            if not (0.0 < value <= 1.0 if low_open else 0.0 <= value <= 1.0):
                bounds = "(0, 1]" if low_open else "[0, 1]"
                raise OptionError(name, f"must be in {bounds}, got {value_text(value)}")
        task = getattr(self, "task", "")
        if self.curriculum and not load_task(task).curriculum:
            raise UsageError(f"task {task!r} has no curriculum (its scene does not read "
                             "Task.difficulty; docs/CURRICULUM.md says how to give it one)")


@dataclass
class PPOArgs(CurriculumOptions):
    task: str = "forward"
    """Task name (``jetbot_rt.tasks.load_task``: a built-in, FILE.py:Class, module:Class)."""
    total_timesteps: int = 40_000
    """Environment steps to collect in total, over all envs."""
    num_envs: int = field(default_factory=lambda: usable_cores())
    """Envs stepped together, each with its own PyBullet client; one per core by default."""
    workers: int | None = None
    """Env worker processes: None (default) runs each env in a process of its own
    (``AsyncVectorEnv``); 0 runs them all in the training process (``SyncVectorEnv``: no
    process start or pickling, one core). With ``ray``: the Ray actors hosting the envs
    (1 .. num_envs; default one per CPU of the cluster, at most num_envs)."""
    ray: str | None = None
    """Env workers as actors on a Ray cluster (``ray_workers.py``): "local" starts Ray on this
    machine, "auto" joins the cluster this machine is part of, HOST:PORT or ray://HOST:PORT
    another; None (default): no Ray, not even imported."""
    ray_max_restarts: int = 3
    """With ``ray``: how many times Ray restarts each env worker (its process or node lost)
    before the run gives up (checkpoint kept, exit 75). Raise it on preemptible nodes."""
    sample_in_workers: bool = True
    """With env worker processes (``workers`` None): each worker runs a copy of the policy
    (CPU, one thread) through the whole rollout and sends it back at once (``sampler.py``),
    instead of a round trip to the learner every step; 2x the env steps/s on 2 cores
    (docs/TRAINING.md, "Speed"). Same PPO: the rollout's weights, SAME_STEP resets, reward
    normalisation in step order. False, ``workers`` 0 and ``ray``: the learner computes each
    step's actions, batched over the envs (on its device)."""
    overlap: bool = False
    """With the policy in the env workers: they collect the next rollout while the learner
    updates on this one (Sample Factory's overlap), with the weights from before the update,
    so a rollout's actions lag the learner's weights by one update. The loss keeps PPO's clip
    around the learner's weights at the update's start and weighs each sample by their
    probability over the collecting weights', truncated at 1 (IMPALA's ``rho``; Hilton et al.
    2021's decoupled PPO); values and advantages are the learner's. For a learner on a GPU or
    spare cores: with every core stepping an env, the update and the workers share them
    (docs/TRAINING.md, "Speed"). Not with a curriculum (its difficulty would reach the
    workers a rollout late)."""
    balance: bool = False
    """With the policy in the env workers: a rollout is ``num_envs * num_steps`` env steps in
    all, each worker stepping until the workers together have them (at least
    ``num_steps // 4``, at most ``2 * num_steps`` each), instead of ``num_steps`` each. A
    worker's scene costs the same for a whole episode and scenes differ (seek's by 1.6x), so
    with equal shares every rollout runs at the pace of its dearest scene. What changes
    (Sample Factory's batches): an env in a cheap scene contributes more steps to a rollout
    than one in a dear scene; the weights, the policy lag and the losses are the same."""
    device: str = "auto"
    """Where the learner (network, rollout buffers, optimizer, the rollout's forward pass)
    runs: "auto" (CUDA when torch sees a GPU, else the CPU), "cpu", "cuda" or "cuda:N". Env
    workers and Ray actors never see it: actions go to them as CPU numpy."""
    out: str = "runs/forward"
    """Directory for checkpoint.pt, policy.onnx, metrics.csv and learning_curve.png."""
    config: Config = field(default_factory=Config)
    """Runtime config: sim physics, actions (max_speed, trim, sign), loop rate."""
    seed: int = 1
    """Seeds torch, the env start noise (env i gets seed + i) and minibatch shuffling."""
    resume: bool = False
    """Continue from ``out/checkpoint.pt`` (model, optimizer, step count, reward scale)."""
    init: str | None = None
    """Start from this checkpoint's network (any task: e.g. forward -> seek); a fresh
    optimizer, step count and reward scale."""
    num_steps: int = 128
    """Steps per env per rollout; a rollout is num_envs * num_steps transitions."""
    learning_rate: float = 1e-3
    """Adam's step size (at the start, see anneal_lr)."""
    anneal_lr: bool = True
    """Decay the learning rate linearly to zero over total_timesteps."""
    gamma: float = 0.99
    """Discount factor."""
    gae_lambda: float = 0.95
    """GAE's lambda."""
    num_minibatches: int = 2
    """Minibatches per rollout in each update epoch (128 frames each with 2 envs)."""
    update_epochs: int = 4
    """Passes over each rollout. With the env at 56x56 the update is most of a step's cost:
    4 epochs of 2 minibatches cost about half of 8 epochs of 4, and forward learns as well
    (docs/TRAINING.md, "Speed")."""
    clip_coef: float = 0.2
    """PPO's ratio clip."""
    target_kl: float | None = None
    """Stop an update's epochs once the last minibatch's approximate KL divergence from the
    collecting policy passes this (CleanRL's ``target_kl``; Stable-Baselines3 checks each
    minibatch against 1.5 times it; None: every epoch runs). On seek the KL grew to 0.05-0.11
    per update while the policy's spread collapsed and its success fell from its peak
    (``benchmarks/results/ppo_lift_h200/``)."""
    ent_coef: float = 0.0
    """Entropy bonus coefficient."""
    vf_coef: float = 0.5
    """Value loss coefficient."""
    max_grad_norm: float = 0.5
    """Gradient norm clip."""
    augment: float = 0.0
    """DrAC's weight (Raileanu et al. 2021; 0: off; 0.1 is DrAC's default): each minibatch's
    frames are also seen shifted by up to 4 pixels of the network's input either way (the
    edge pixels repeated), and the loss adds ``augment`` times how far the policy's mean (and
    the image critic's value) moves from the unshifted frame's. The surrogate itself stays on
    the collected frames, so PPO's ratio keeps its meaning. Against over-fitting the scenes
    trained on."""
    predict_state: float = 0.0
    """With ``critic`` "state": the weight of an auxiliary loss (0: off) that trains a linear
    head on the actor's image features to predict the critic's privileged state (for seek the
    goal's distance and bearing), each value standardised over the rollout (its mean and
    spread), the squared error averaged over the values. A dense,
    supervised signal for the encoder to find what the task's state depends on, as Lample and
    Chaplot (2017) predicted game features from frames; the head is a training-time part,
    like the critic, and the exported actor is unchanged. No expert is involved: the target
    is the simulator's state, not an action."""
    reward_transform: str = "symlog"
    """"symlog": learn from sign(r) * ln(1 + |r|) of the task reward (then shaping, scale
    and clip); "none": the task reward as is. The forward reward spans -27 .. 1e4+;
    compressed, a step closer is visible at any distance."""
    shaping_coef: float = 0.0
    """Progress shaping ``c * (d - d')`` per step, d the env's ``distance`` (forward and seek:
    the robot-goal distance in m; forward trains with 1000, seek with 10) (it sums
    to ``c * (d_start - d_end)`` over an episode, so it ranks whole episodes as the distance
    they close does). Far from the block forward's reward is nearly flat (-27.0 at 0.9 m,
    -24.7 at 0.6 m): without this, a random policy's wheel commands leave no trace in the
    returns that the value function's error does not swamp. 0 (the default for a task that
    sets none) turns it off."""
    aim_coef: float = 0.0
    """Aim shaping ``k * (e - e')`` per step, e the env's ``aim_error``: how far (m) the block
    lies off the robot's line of travel. Progress alone barely rewards steering (heading
    8 degrees off costs 1 % of the progress per step) and the payoff of aiming right -- the
    huge reward at the block -- comes ~300 steps later, beyond gamma's horizon; this pays for
    a correction the step it is made. Potential-based, it sums to ``k * (e_start - e_end)``
    and cannot be farmed by wiggling. forward trains with 300, seek with 5; 0 turns it off."""
    success_bonus: float = 0.0
    """Added on the step that ends an episode with success (tasks with early_end)."""
    fail_penalty: float = 0.0
    """Subtracted on the step that ends an episode as failed (goal pushed away)."""
    step_penalty: float = 0.0
    """Subtracted on every step (Habitat's slack reward, Savva et al. 2019; 0: off). Tried
    because standing still costs nothing: many held-out misses of seek's PPO policies never
    left the start (``benchmarks/seek_misses.py``); on seek it did not help
    (``benchmarks/results/ppo_freeze_h200/``). Where a push ends the episode, a cost per step
    also makes ending early by a push cheaper than waiting out the time."""
    reward_clip: float = 10.0
    """Clip of the scaled reward (reward / running std of the discounted return)."""
    checkpoint_every: int = 5
    """Save the checkpoint every this many updates (and always at the end)."""
    torch_threads: int = 1
    """Learner threads while collecting; the env workers need the other cores."""
    update_threads: int = field(default_factory=lambda: usable_cores())
    """Learner threads during the update, when the env workers are idle: the cores this
    process may run on (its CPU affinity), not all the machine's; more threads than cores
    made PPO 10x slower (2 cores of 16 under taskset: 43 env steps/s instead of ~450)."""
    critic: str = "image"
    """What the value function reads: "image", the camera image (a value head on the
    actor's features, one network); "state", the simulator's privileged state
    (``Task.critic_state``: for seek the goal's distance and bearing, the speed, the
    latencies, ...) through an MLP of its own, the asymmetric actor-critic of Pinto et al.
    2018. The actor and the exported ONNX are the same either way: one image in, mu out.
    For tasks with a critic state (forward, seek, follow, avoid)."""
    critic_hidden: int = 64
    """With critic "state": the width of the critic MLP's two hidden layers."""
    progress: bool = True
    """Show a progress bar."""
    model: ModelConfig = field(default_factory=ModelConfig)
    """The network (``model.py``)."""

    @property
    def shaping(self) -> Shaping:
        return Shaping(self.reward_transform, self.shaping_coef, self.aim_coef,
                       self.success_bonus, self.fail_penalty, self.step_penalty)

    @property
    def samples_in_workers(self) -> bool:
        """Whether the env workers run the policy through whole rollouts
        (``rollout.WorkerRollouts``): ``sample_in_workers`` with worker processes, no Ray."""
        return self.sample_in_workers and self.ray is None and self.workers != 0

    def validate(self) -> None:
        """``OptionError`` for the first option out of range (before any env starts)."""
        check_fields(self, SIGNED)
        self.validate_curriculum()
        if self.ray is not None and self.workers is not None and \
                not 0 < self.workers <= self.num_envs:
            raise OptionError("workers", f"with ray must be 1 .. num_envs ({self.num_envs}), "
                                         f"got {self.workers}")
        if self.overlap and not self.samples_in_workers:
            raise OptionError("overlap", "needs the policy in the env workers (worker "
                                         "processes, sample_in_workers, no ray)")
        if self.balance and not self.samples_in_workers:
            raise OptionError("balance", "needs the policy in the env workers (worker "
                                         "processes, sample_in_workers, no ray)")
        if self.overlap and self.curriculum:
            raise OptionError("overlap", "cannot run with curriculum: the difficulty would "
                                         "reach the workers a rollout late")
        if self.ray is None and self.workers not in (None, 0, self.num_envs):
            raise OptionError("workers", f"must be 0 (envs in this process) or num_envs "
                                         f"({self.num_envs}, one process each), got "
                                         f"{self.workers}")
        if self.ray_max_restarts < 0:
            raise OptionError("ray_max_restarts", f"must be >= 0, got {self.ray_max_restarts}")
        if self.augment < 0:
            raise OptionError("augment", f"must be >= 0, got {self.augment}")
        if self.step_penalty < 0:
            raise OptionError("step_penalty", f"must be >= 0, got {self.step_penalty}")
        if self.target_kl is not None and not self.target_kl > 0:
            raise OptionError("target_kl", f"must be > 0, got {self.target_kl}")
        if self.predict_state < 0:
            raise OptionError("predict_state", f"must be >= 0, got {self.predict_state}")
        if self.predict_state > 0 and self.critic != "state":
            raise OptionError("predict_state", "needs critic \"state\": the state it predicts "
                                               "is the critic's")
        if self.reward_transform not in REWARD_TRANSFORMS:
            raise OptionError("reward_transform", f"must be one of "
                                                  f"{', '.join(REWARD_TRANSFORMS)}, got "
                                                  f"{value_text(self.reward_transform)}")
        critic = critic_config(self)
        if critic is not None and \
                self.model.parameter_count() + critic.parameter_count(self.model) > \
                MAX_PARAMETERS:
            raise OptionError("critic_hidden", f"makes the network and its critic larger than "
                                               f"the {MAX_PARAMETERS:,} parameters a "
                                               "checkpoint may hold")


def critic_config(options: PPOArgs) -> CriticConfig | None:
    """The critic ``options`` ask for: None for ``critic`` "image" (the value head on the
    image features), else a ``CriticConfig`` as wide as the task's critic state.
    ``OptionError`` for an unknown ``critic``; ``UsageError`` for "state" on a task without
    a critic state (``Task.critic_state_names`` empty)."""
    if options.critic not in CRITICS:
        raise OptionError("critic", f"must be one of {', '.join(CRITICS)}, got "
                                    f"{value_text(options.critic)}")
    if options.critic == "image":
        return None
    task = load_task(options.task)
    if not task.critic_state_names:
        raise UsageError(f"--critic state: task {options.task!r} has no privileged critic "
                         "state (its Task.critic_state_names is empty; docs/TASKS.md says how "
                         "to give it one)")
    if not 1 <= options.critic_hidden <= MAX_HIDDEN:
        raise OptionError("critic_hidden", f"must be 1 .. {MAX_HIDDEN}, got "
                                           f"{options.critic_hidden}")
    return CriticConfig(len(task.critic_state_names), options.critic_hidden,
                        options.predict_state > 0)


TASK_DEFAULTS: dict[str, dict[str, Any]] = {name: load().training for name, load in
                                            BUILTIN.items()}
"""Per built-in task, the PPOArgs values that differ from the dataclass defaults (each task's
``Task.training``); the command line and a ``[train]`` table override them."""


def ppo_args(task: str, overrides: dict[str, Any] | None = None) -> PPOArgs:
    """``PPOArgs`` for ``task``: dataclass defaults, then ``TASK_DEFAULTS[task]``, then
    ``overrides`` (a ``[train]`` table or command-line values; ``model`` a dict)."""
    loaded = load_task(task)
    defaults = {"out": f"runs/{loaded.short_name()}", **loaded.training}
    return _build(PPOArgs, "training", task, defaults, overrides)


def _build(cls: Any, what: str, task: str, defaults: dict[str, Any],
           overrides: dict[str, Any] | None) -> Any:
    """``cls`` for ``task``: ``defaults`` then ``overrides`` (each with an optional
    ``model`` dict); unknown keys of either level are refused, then every value is checked."""
    load_task(task)
    values = {k: v for k, v in defaults.items() if k != "model"}
    model = dict(defaults.get("model", {}))
    for key, value in (overrides or {}).items():
        if key != "model":
            values[key] = value
        elif isinstance(value, dict):
            model.update(value)
        else:
            raise OptionError("model", f"must be a table of network options, got "
                                       f"{value_text(value)}")
    names = {f.name for f in fields(cls)} - {"task", "config", "model"}
    unknown = sorted(str(key) for key in values if key not in names)
    if unknown:
        raise UsageError(f"unknown {what} option(s) {', '.join(unknown)} "
                         f"(known: {', '.join(sorted(names))})")
    built = replace(cls(), task=task, **values,
                    model=ModelConfig.from_dict({**ModelConfig().to_dict(), **model}))
    built.validate()
    return built


def check_fields(options: Any, signed: tuple[str, ...] = ()) -> None:
    """Each field of the dataclass ``options`` (but ``task``, ``config``, ``model``) of its
    annotated type: an ``int`` not a bool and > 0 unless named in ``signed``, a ``float``
    finite, ``X | None`` also None. ``OptionError`` names the first that is not."""
    for spec in fields(options):
        if spec.name in ("task", "config", "model"):
            continue
        value, kind = getattr(options, spec.name), str(spec.type)
        if kind.endswith(" | None"):
            if value is None:
                continue
            kind = kind[: -len(" | None")]
        if kind == "int":
            _check_int(spec.name, value)
            if value <= 0 and spec.name not in signed:
                raise OptionError(spec.name, f"must be > 0, got {value}")
        elif kind == "float" and (isinstance(value, bool) or not isinstance(value, (int, float))
                                  or not math.isfinite(value)):
            raise OptionError(spec.name, f"must be a finite number, got {value_text(value)}")
        elif kind in ("bool", "str") and type(value).__name__ != kind:
            raise OptionError(spec.name, f"must be a {kind}, got {value_text(value)}")


@dataclass
class DAggerArgs(CurriculumOptions):
    task: str = "seek"
    """Task name; the task needs an expert (``Task.expert``: seek's)."""
    out: str = "runs/seek"
    """Directory for checkpoint.pt, policy.onnx, metrics.csv and learning_curve.png."""
    config: Config = field(default_factory=Config)
    """Runtime config: sim physics, actions (max_speed, trim, sign), loop rate."""
    seed: int = 1
    """Seeds torch, the episodes' scenes (iteration i, env j: seed * 100000 + i * 1000 + j)
    and minibatch shuffling."""
    resume: bool = False
    """Continue from ``out/checkpoint.pt`` (network, optimizer, iteration); the aggregated
    frames are not kept, so the dataset starts again from the student's rollouts."""
    init: str | None = None
    """Start from this checkpoint's network (any task)."""
    num_envs: int = field(default_factory=lambda: usable_cores())
    """Envs stepped together, each in a worker process of its own; one per core by default."""
    workers: int | None = None
    """0: all envs in the training process (SyncVectorEnv); None: one process per env."""
    iterations: int = 40
    """DAgger iterations (iteration 0: the expert drives)."""
    steps_per_iteration: int = 3000
    """Env steps collected per iteration, over all envs (finished episodes only count)."""
    expert_noise: float = 0.3
    """Std of the Gaussian noise on the expert's action while it drives (iteration 0 and the
    beta share): states off the expert's path, with their corrections."""
    beta: float = 0.5
    """Share of episodes the expert drives in iteration 1; halves every iteration."""
    expert_sees: str = "frame"
    """The state the expert labels and drives on: "frame", the one the frame shows (the
    camera's latency ago: labels the student can read off its frame) or "now", the true
    state at the frame's delivery (``dagger_sampler.FrameState``)."""
    train_samples: int = 16_000
    """Frames regressed on after each iteration, in shuffled passes over the aggregate (a
    fixed cost: epochs over a growing aggregate would make each iteration slower than the
    last)."""
    batch_size: int = 128
    """Frames per Adam step."""
    learning_rate: float = 1e-3
    """Adam's step size in the first iteration."""
    final_learning_rate: float | None = None
    """Adam's step size in the last iteration, reached by geometric steps from
    ``learning_rate`` (None: constant). Late iterations then refine the student instead of
    swinging it from one rollout to the next."""
    photometric_jitter: float = 0.3
    """Each regressed frame's brightness and contrast scaled by factors drawn from
    1 +- this, each colour channel by 1 +- half of it (0: frames as rendered): lighting the
    randomization draws once per episode varies for every frame."""
    stop_weight: float = 4.0
    """Loss weight of frames the expert labels stop or back off (both wheels <= 0): few, and
    the ones that decide whether the block is pushed."""
    turn_weight: float = 1.0
    """Loss weight of frames the expert labels a turn on the spot (one wheel backwards, the
    other forwards): avoid's "blocked", rare and the ones that decide a touch, which its
    student under-answered ((+0.5, +0.9) for (-0.9, +0.9)). 1: weighed as any frame."""
    mirror: float = 0.0
    """The probability that a regressed frame is seen in a mirror (columns reversed, the
    label's wheels swapped), for frames on which the expert's rule has no side
    (``Expert.symmetric``: avoid's in the open). Its student leaned left in the open, its
    only turn on the spot being left. 0: never."""
    stop_distance: float | None = None
    """m; the expert commands zero from this distance to the goal on (seek's ``Expert``).
    This and the five below replace the field of their name in the task's expert where it
    has one; None (the default) keeps the expert's own value."""
    min_forward: float | None = None
    """The expert's slowest forward command while driving (seek's ``Expert``; avoid's and
    follow's experts have one too); times max_speed it must stay above the dead-band it
    trains with."""
    search_bearing_deg: float | None = None
    """Degrees; the expert searches beyond this bearing error (seek's ``Expert``; 30 through the
    pinhole lens)."""
    search_left: float | None = None
    """The expert's left wheel command while the goal is out of view (seek's ``Expert``)."""
    search_right: float | None = None
    """The expert's right wheel command while the goal is out of view (seek's ``Expert``)."""
    backoff_distance: float | None = None
    """m; the expert backs away closer than this (seek's ``Expert``; 0: never)."""
    snapshots: int = 0
    """Also export ``policy_<iteration>.onnx`` every this many iterations (0: never)."""
    device: str = "cpu"
    """Where the regression runs: "cpu" (default: the same weights from the same seed, byte
    for byte), "auto" (CUDA when torch sees a GPU), "cuda" or "cuda:N". The rollouts run in
    the env workers on the CPU either way."""
    torch_threads: int = 1
    """Learner threads during the regression (the env workers are idle then). One: on two
    shared cores two threads spin more than they compute (docs/TRAINING.md)."""
    progress: bool = True
    """Show a progress bar."""
    model: ModelConfig = field(default_factory=ModelConfig)
    """The network (``model.py``)."""

    def validate(self) -> None:
        """``OptionError`` for the first option out of range (before any env starts)."""
        if load_task(self.task).expert() is None:
            raise UsageError(f"task {self.task!r} has no expert for DAgger (its Task.expert() "
                             "returns None); train it with --algo ppo")
        check_fields(self, SIGNED)
        self.validate_curriculum()
        if self.workers not in (None, 0, self.num_envs):
            raise OptionError("workers", f"must be 0 or num_envs ({self.num_envs}), got "
                                         f"{self.workers}")
        if self.snapshots < 0:
            raise OptionError("snapshots", f"must be >= 0, got {self.snapshots}")
        for name in ("stop_weight", "turn_weight"):  # a negative one trains away from them
            if getattr(self, name) < 0:
                raise OptionError(name, f"must be >= 0, got {getattr(self, name):g}")
        if not 0.0 <= self.mirror <= 1.0:
            raise OptionError("mirror", f"must be within [0, 1], got {self.mirror:g}")
        if self.mirror > 0 and not hasattr(load_task(self.task).expert(), "symmetric"):
            raise OptionError("mirror", f"needs an expert with symmetric(info); the "
                                        f"{self.task} task's has none, so no frame would "
                                        "be mirrored")
        if self.expert_sees not in EXPERT_SEES:
            raise OptionError("expert_sees", f"must be one of {', '.join(EXPERT_SEES)}, got "
                                             f"{value_text(self.expert_sees)}")


def dagger_args(task: str, overrides: dict[str, Any] | None = None) -> DAggerArgs:
    """``DAggerArgs`` for ``task`` with ``overrides`` (a ``[train]`` table, then flags)."""
    return _build(DAggerArgs, "DAgger", task, {"out": f"runs/{load_task(task).short_name()}"},
                  overrides)


def read_config_file(path: str | None) -> tuple[Config, dict[str, Any]]:
    """The runtime config of a TOML file and its ``[train]`` table (the defaults and an empty
    table without a file)."""
    if path is None:
        return Config(), {}
    data = read_toml(path)
    table = data.get("train", {})
    if not isinstance(table, dict):
        raise UsageError(f"config {path}: [train] must be a table")
    try:
        return from_dict(data), table
    except UsageError as exc:
        raise UsageError(f"config {path}: {exc}") from None

"""Runtime configuration: a TOML file loaded into typed dataclasses, then command-line overrides.

Every key is declared with its type and its valid range (``config/schema.py``, the engine); an
unknown section or key, a wrong type or an out-of-range value raises ``UsageError`` naming the
key (``[loop] rate_hz``). The annotations are written ``Optional[...]`` and ``List[...]``, not
``X | None`` and ``list[...]``: the robot's Python 3.8 evaluates them here.
"""

from __future__ import annotations

import dataclasses
import shlex
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, List, Optional

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10 (JetPack 6) path
    import tomli as tomllib

from jetbot_rt.config import safe_file
from jetbot_rt.config.schema import check, one_of, pair, set_value, within
from jetbot_rt.errors import UsageError
from jetbot_rt.monitor.config import MonitorConfig
from jetbot_rt.sim.config import RandomizeConfig, SimConfig

MOTOR_LAYOUTS = ("waveshare", "adafruit_motorhat")
DEFAULT_FRAME_AGE_S = 0.15
DEFAULT_WATCHDOG_MIN_S = 0.1
FRAME_AGE_INTERVALS = 1.5
"""A frame-age limit below 1.5 frame intervals refuses good frames on ordinary jitter."""
LAYOUTS = ("NHWC", "NCHW")
COLOR_ORDERS = ("RGB", "BGR")
PIXEL_RANGES = ("0-255", "0-1", "-1-1")


def _camera_source_ok(value: str) -> bool:
    if value.startswith("gst:") and len(value.strip()) > 4:
        try:
            shlex.split(value[4:])  # as the camera will split it for gst-launch
        except ValueError as exc:  # "No closing quotation", "No escaped character"
            raise ValueError(f"a GStreamer pipeline gst-launch can parse ({exc}), "
                             f"got {value!r}") from None
        return True
    return value == "csi" or (value.startswith("usb:") and len(value) > 4)


SIM_WATCHDOG_MIN_S = 1.0
"""The sim backend's floor for the default watchdog timeout. A simulated world stands still
while the process is not scheduled, so a desktop's hiccup (seen: 0.103 s at load 1.3) is no
hazard there; 1 s still ends a hung policy as the robot would, only later."""


@dataclass
class LoopConfig:
    rate_hz: float = field(default=30.0, metadata=within(1.0, 100.0, " Hz"))
    """Control rate; ticks sit on absolute monotonic deadlines 1/rate_hz apart."""
    max_frame_age: Optional[float] = field(default=None, metadata=within(0.005, 10.0, " s"))
    """Seconds; a frame older than this at the start of a tick is refused (a fault).
    Default: 0.15 s, or 1.5 frame intervals where frames come slower (1.5 periods: the sim
    renders once per tick; 1.5 / [camera] fps: the camera); at least that if set."""
    watchdog_timeout: Optional[float] = field(default=None, metadata=within(0.01, 10.0, " s"))
    """Seconds without a completed tick before the watchdog latches the safe stop.
    Default: three periods, at least 0.1 s (on the sim backend at least 1 s); at least two
    periods if set."""
    warmup_timeout: float = field(default=300.0, metadata=within(0.1, 3600.0, " s"))
    """Seconds the warm-up may take before the policy is refused; the first inference on a
    Jetson may build a TensorRT engine, which takes minutes."""
    warmup_runs: int = field(default=3, metadata=within(1, 100))
    """Timed inferences before driving; if the fastest is slower than a period, refuse the run."""

    @property
    def period(self) -> float:
        return 1.0 / self.rate_hz

    @property
    def watchdog_timeout_s(self) -> float:
        """The watchdog timeout on the robot."""
        return self.watchdog_timeout_for(simulated=False)

    def watchdog_timeout_for(self, simulated: bool) -> float:
        """``watchdog_timeout`` if set, else three periods, at least 0.1 s on the robot and
        ``SIM_WATCHDOG_MIN_S`` on a simulated one."""
        if self.watchdog_timeout is not None:
            return self.watchdog_timeout
        return max(3.0 * self.period, SIM_WATCHDOG_MIN_S if simulated else DEFAULT_WATCHDOG_MIN_S)


@dataclass
class PolicyConfig:
    path: Optional[str] = field(default=None, metadata=check(bool, "a file name, not empty"))
    """ONNX file; default (key absent): the policy bundled in the package."""
    layout: Optional[str] = field(default=None, metadata=one_of(LAYOUTS))
    """Override the input layout read from the model."""
    color_order: Optional[str] = field(default=None, metadata=one_of(COLOR_ORDERS))
    """Override the channel order the model expects (metadata, else RGB)."""
    pixel_range: Optional[str] = field(default=None, metadata=one_of(PIXEL_RANGES))
    """Override the pixel range the model expects (metadata, else 0-255)."""
    clip: Optional[float] = field(default=None, metadata=within(0.001, 1e6))
    """Clip the input values to [-clip, clip] after scaling to pixel_range, as training did:
    rl_games' clip_observations (Isaac Lab's clip_obs, 5.0) clips raw 0..255 pixels to 0..5."""
    threads: int = field(default=1, metadata=within(1, 64))
    """onnxruntime CPU threads. One keeps a tick from waiting on a worker thread that the
    scheduler has not woken yet; raise it for a large model on the CPU."""
    providers: Optional[List[str]] = None
    """onnxruntime execution providers in order; default TensorRT, CUDA, CPU (those present)."""


@dataclass
class ActionsConfig:
    max_speed: Optional[float] = field(
        default=None, metadata=within(0, 1, open_low=True)
    )
    """Duty at |mu| = 1. Default: the model's metadata, else 0.1."""
    trim: List[float] = field(
        default_factory=lambda: [1.0, 1.0],
        metadata=pair(0, 2),
    )
    """[left, right] gain per wheel, to even out a weaker motor."""
    sign: List[int] = field(
        default_factory=lambda: [1, 1],
        metadata=check(lambda v: len(v) == 2 and all(x in (1, -1) for x in v),
                       "two values, each 1 or -1"),
    )
    """[left, right]: -1 for a motor wired the wrong way round."""
    deadband: float = field(default=0.0, metadata=within(0, 0.5))
    """Duty below which a wheel does not turn (``jetbot-rt calibrate`` fits it, as ``[sim]
    deadband`` in its output). Every duty that is not zero is lifted by it, ``sign(d) * (|d|
    + deadband)``, so a wheel's speed follows the command as on a motor without a dead-band;
    zero stays zero. 0 (the default): off."""


@dataclass
class MotorsConfig:
    layout: str = field(default="waveshare", metadata=one_of(MOTOR_LAYOUTS))
    i2c_bus: int = field(default=1, metadata=within(0, 255))
    address: int = field(default=0x60, metadata=within(0x03, 0x77, spelled="0x03..0x77"))
    left_motor: int = field(default=1, metadata=within(1, 4))
    """adafruit_motorhat only: which of MotorKit's motor1..motor4 is the left wheel."""
    right_motor: int = field(default=2, metadata=within(1, 4))
    pwm_frequency: float = field(
        default=1600.0, metadata=within(24, 1600, " Hz")
    )
    """MotorKit's default; the chip's prescaler tops out at about 1526 Hz and takes the nearest."""
    i2c_retries: int = field(default=3, metadata=within(0, 20))
    """Extra attempts after a transient I2C OSError before it counts as a fault."""
    emulator: Optional[str] = field(default=None, metadata=check(bool, "a file name, not empty"))
    """Tests and dry runs only: the register-level PCA9685 emulator whose registers live in
    this file stands in for the board on ``i2c_bus`` (``jetbot_rt.testing``; every command
    says so on stdout, ``run`` in its ``start`` event too). ``--board-emulator`` overrides."""


@dataclass
class CameraConfig:
    source: str = field(
        default="csi",
        metadata=check(_camera_source_ok, '"csi", "usb:/dev/videoN" or "gst:<pipeline>"'),
    )
    sensor_id: int = field(default=0, metadata=within(0, 7))
    capture_width: int = field(default=1280, metadata=within(16, 8192))
    capture_height: int = field(default=720, metadata=within(16, 8192))
    fps: float = field(default=30.0, metadata=within(1.0, 240.0))
    flip_method: int = field(default=0, metadata=within(0, 7))
    start_timeout: float = field(default=10.0, metadata=within(0.1, 600.0, " s"))
    """Seconds to wait for the first frame before the camera counts as not started."""


@dataclass
class TelemetryConfig:
    path: Optional[str] = field(default=None, metadata=check(bool, "a file name, not empty"))
    """JSON Lines file, one record per tick plus events; none by default. A run that starts
    moves the previous file to ``<path>.1``; a start refused before that only appends."""


@dataclass
class RecordConfig:
    path: Optional[str] = None
    """Directory to record every tick's frame and record into (docs/RECORDING.md); none by
    default. It must not exist or be empty; ``{time}`` becomes the start time (UTC), so that
    each run of the service records into a directory of its own."""
    queue_frames: int = field(default=64, metadata=within(1, 10000))
    """Frames that may wait for the disk; beyond that a tick's frame is dropped and counted
    (the tick itself never waits)."""
    min_free_mb: float = field(default=64.0, metadata=within(0, None))
    """The recording stops (the robot drives on) when the disk has less free space than this,
    so that a full SD card never starves the system's own logs."""
    codec: str = field(default="huffyuv", metadata=one_of(("huffyuv", "ffv1")))
    """Lossless video codec of the frames: "huffyuv" (little CPU, larger files) or "ffv1"
    (a quarter to a half smaller, 4-9 times the CPU; docs/RECORDING.md)."""


@dataclass
class Config:
    loop: LoopConfig = field(default_factory=LoopConfig)
    policy: PolicyConfig = field(default_factory=PolicyConfig)
    actions: ActionsConfig = field(default_factory=ActionsConfig)
    motors: MotorsConfig = field(default_factory=MotorsConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    telemetry: TelemetryConfig = field(default_factory=TelemetryConfig)
    record: RecordConfig = field(default_factory=RecordConfig)
    monitor: MonitorConfig = field(default_factory=MonitorConfig)
    sim: SimConfig = field(default_factory=SimConfig)
    randomize: RandomizeConfig = field(default_factory=RandomizeConfig)

    @property
    def frame_interval(self) -> float:
        """The longest time between two new frames: the sim renders one per tick, the camera
        one per 1 / ``[camera] fps`` (the conservative union, whichever backend runs)."""
        return max(self.loop.period, 1.0 / self.camera.fps)

    @property
    def max_frame_age_s(self) -> float:
        """``[loop] max_frame_age``, or its default that follows the frame interval."""
        if self.loop.max_frame_age is not None:
            return self.loop.max_frame_age
        return max(DEFAULT_FRAME_AGE_S, FRAME_AGE_INTERVALS * self.frame_interval)

    def validate(self) -> None:
        """Cross-key checks: values each in range that together cannot run. One line naming
        the keys, as ``UsageError``."""
        loop, period = self.loop, self.loop.period
        if loop.watchdog_timeout is not None and loop.watchdog_timeout < 2 * period:
            raise UsageError(
                f"[loop] watchdog_timeout {loop.watchdog_timeout:g} s is shorter than two "
                f"periods at [loop] rate_hz {loop.rate_hz:g} ({2 * period:.3g} s): it would "
                "trip between two good ticks"
            )
        needed = FRAME_AGE_INTERVALS * self.frame_interval
        if loop.max_frame_age is not None and loop.max_frame_age < needed:
            raise UsageError(
                f"[loop] max_frame_age {loop.max_frame_age:g} s is shorter than "
                f"{FRAME_AGE_INTERVALS:g} frame intervals ({needed:.3g} s at [loop] rate_hz "
                f"{loop.rate_hz:g} and [camera] fps {self.camera.fps:g}): good frames would "
                "be refused as stale"
            )

    def validate_service_watchdog(self, ping_interval: float | None) -> None:
        """Under systemd (``WatchdogSec``): every ``WATCHDOG=1`` is paid for by a completed
        tick and goes out every ``ping_interval`` (WatchdogSec / 3); ticks further apart
        than that would have systemd kill a healthy run."""
        if ping_interval is not None and self.loop.period > ping_interval:
            raise UsageError(
                f"[loop] rate_hz {self.loop.rate_hz:g} puts ticks {self.loop.period:.3g} s "
                f"apart, but the unit's WatchdogSec ({3 * ping_interval:g} s) needs a "
                f"WATCHDOG=1 every {ping_interval:.3g} s: raise rate_hz to at least "
                f"{1 / ping_interval:.3g} or WatchdogSec"
            )


FOREIGN_SECTIONS = ("train",)
"""Sections another command reads from the same file (``[train]``: ``jetbot-train train``);
the runtime skips them."""


def from_dict(data: dict[str, Any]) -> Config:
    config = Config()
    sections = {f.name for f in dataclasses.fields(config)}
    for section, values in data.items():
        if section in FOREIGN_SECTIONS:
            continue
        if section not in sections:
            raise UsageError(
                f"unknown section [{section}] (known sections: {', '.join(sorted(sections))})"
            )
        if not isinstance(values, dict):
            raise UsageError(f"[{section}] must be a table")
        for key, value in values.items():
            set_value(getattr(config, section), section, key, value)
    return config


MAX_CONFIG_BYTES = 256 * 1024
"""A config is a few hundred bytes; anything larger is refused before it is parsed."""


def read_config_text(path: Path) -> str:
    """The text of a config file in bounded time and memory (``safe_file``: regular file only,
    never blocking, at most ``MAX_CONFIG_BYTES``, UTF-8), or ``UsageError``."""
    return safe_file.read_text(path, "config", MAX_CONFIG_BYTES)


def read_toml(path: str | Path) -> dict[str, Any]:
    """The TOML file as a dict (read by ``read_config_text``); bad files are a ``UsageError``."""
    path = Path(path)
    text = read_config_text(path)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise UsageError(f"config {path} is not valid TOML: {exc}") from None
    except ValueError as exc:  # an integer of more than 4300 digits (Python >= 3.11's limit)
        raise UsageError(f"config {path} is not valid TOML: {str(exc)[:80]}") from None
    except RecursionError:
        raise UsageError(f"config {path} is not valid TOML: nested too deeply") from None


def load_config(path: str | Path | None) -> Config:
    """Read a TOML file (or return the defaults when ``path`` is None)."""
    if path is None:
        return Config()
    data = read_toml(path)
    try:
        return from_dict(data)
    except UsageError as exc:
        raise UsageError(f"config {path}: {exc}") from None

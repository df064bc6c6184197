"""Fault matrix, bad input: every config key with a bad value, broken models, cameras that
cannot start, conflicting flags and a second runtime. Each is exit code 2, one line on stderr
naming the problem, no traceback, and not a single motor command (docs/SAFETY.md).

tests/test_run_sim.py covers the first examples of each kind; this file goes through all.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import uuid
from pathlib import Path

import policy_models
import pytest
from runner import RuntimeProcess, processes_with, run_cli, wait_for

from jetbot_rt.cli import main
from jetbot_rt.config import schema
from jetbot_rt.config.sections import Config
from jetbot_rt.workstation import sim_problem

# Every key with a value of the right type but out of its range (or not one of its choices).
OUT_OF_RANGE = {
    ("loop", "rate_hz"): 0,
    ("loop", "max_frame_age"): -0.1,
    ("loop", "watchdog_timeout"): 0,
    ("loop", "warmup_timeout"): 0,
    ("loop", "warmup_runs"): 101,
    ("policy", "path"): None,  # any string is a path: a missing one is a model case below
    ("policy", "layout"): "NWHC",
    ("policy", "color_order"): "GBR",
    ("policy", "pixel_range"): "0-65535",
    ("policy", "clip"): 0,
    ("policy", "threads"): 0,
    ("policy", "providers"): None,  # any list of names: unknown ones are skipped, CPU remains
    ("actions", "max_speed"): 1.5,
    ("actions", "trim"): [1.0, 2.5],
    ("actions", "sign"): [1, 0],
    ("actions", "deadband"): 0.6,
    ("motors", "layout"): "l298n",
    ("motors", "i2c_bus"): 256,
    ("motors", "address"): 0x80,
    ("motors", "left_motor"): 5,
    ("motors", "right_motor"): 0,
    ("motors", "pwm_frequency"): 2000.0,
    ("motors", "i2c_retries"): 21,
    ("motors", "emulator"): "",
    ("camera", "source"): "v4l2",
    ("camera", "sensor_id"): 8,
    ("camera", "capture_width"): 8,
    ("camera", "capture_height"): 9000,
    ("camera", "fps"): 0,
    ("camera", "flip_method"): 8,
    ("camera", "start_timeout"): 0,
    ("telemetry", "path"): None,  # any string is a path: an unwritable one is a case below
    ("monitor", "listen"): "robot.local:8080",
    ("monitor", "token_file"): "",
    ("monitor", "max_fps"): 0,
    ("monitor", "drive"): None,  # true or false
    ("sim", "physics_hz"): -240.0,
    ("sim", "motor_gain"): 0,
    ("sim", "motor_tau"): -0.05,
    ("sim", "seed"): None,  # any integer is a seed
    ("sim", "task"): None,  # any name: an unknown task is refused when the scene is built
    ("sim", "camera_stall_after"): 0,
    ("sim", "blackout"): [2.0, 1.0],
    ("sim", "supersample"): 5,
    ("record", "path"): None,  # any string is a directory: an unusable one is tests/test_record
    ("record", "queue_frames"): 0,
    ("record", "min_free_mb"): -1.0,
    ("record", "codec"): "mjpg",
    ("sim", "wheel_gain"): [1.0, 0.0],
    ("sim", "deadband"): 1.0,
    ("sim", "latency"): 1.5,
    ("sim", "camera_latency"): -0.1,
    ("sim", "stall_torque"): 0.0,
    ("sim", "camera_pitch_deg"): 90.0,
    ("sim", "camera_height"): 0.01,
    ("sim", "camera_vfov_deg"): 170.0,
    ("sim", "floor_color"): [0.5, 0.5, 1.5],
    ("sim", "floor_texture"): "marble",
    ("sim", "wall_color"): [0.5, 0.5],
    ("sim", "block_color"): [-0.1, 0.0, 0.0],
    ("sim", "light_direction"): [0.0, 0.0, 0.0],
    ("sim", "light_intensity"): 4.0,
    ("sim", "image_noise"): 2.0,
    ("sim", "image_blur"): 0.5,
    ("sim", "image_brightness"): -2.0,
    ("sim", "image_contrast"): 5.0,
    ("sim", "lens"): "fish-eye",
    ("sim", "lens_focal"): 0.0,
    ("sim", "lens_center"): [0.5, 0.9],
    ("sim", "lens_k1"): 1.5,
    ("sim", "lens_k2"): -1.5,
    ("sim", "lens_k3"): 2.0,
    ("sim", "lens_k4"): -2.0,
    ("randomize", "enabled"): None,  # true or false
    ("randomize", "wheel_gain"): [1.2, 0.8],
    ("randomize", "motor_gain"): [0.0, 1.0],
    ("randomize", "deadband"): [0.0, 1.0],
    ("randomize", "latency"): [0.0, 2.0],
    ("randomize", "camera_latency"): [-0.1, 0.1],
    ("randomize", "stall_torque"): [0.0, 0.1],
    ("randomize", "camera_pitch_deg"): [0.8, 4.0],
    ("randomize", "camera_height"): [0.1, 1.0],
    ("randomize", "camera_vfov_deg"): [0.1, 1.0],
    ("randomize", "floor_color"): [0.6, 6.0],
    ("randomize", "floor_plain"): 1.5,
    ("randomize", "plain_floor_grey"): [0.2, 1.5],
    ("randomize", "plain_floor_tint"): [0.7, 6.0],
    ("randomize", "deadband_lift"): [-0.5, 0.05],
    ("randomize", "wall_color"): [-1.0, 1.3],
    ("randomize", "block_color"): [1.1, 0.8],
    ("randomize", "tint"): [0.9, 9.0],
    ("randomize", "light_elevation_deg"): [30.0, 100.0],
    ("randomize", "light_intensity"): [0.7, 4.0],
    ("randomize", "image_noise"): [0.0, 2.0],
    ("randomize", "image_blur"): [0.0, 0.5],
    ("randomize", "image_brightness"): [-2.0, 0.1],
    ("randomize", "image_contrast"): [0.8, 4.0],
    ("randomize", "lens_focal"): [0.4, 1.0],
    ("randomize", "lens_k1"): [-0.6, 0.0],
    ("randomize", "lens_k2"): [0.0, 0.6],
    ("sim", "wall_texture"): "marble",
    ("sim", "skirting_color"): [0.5, 0.5, 1.5],
    ("sim", "clutter"): 13,
    ("sim", "lamps"): 5,
    ("sim", "window_light"): 2.5,
    ("sim", "light_color"): [1.0, -0.1, 1.0],
    ("sim", "shadows"): None,  # true or false
    ("sim", "look_seed"): -1,
    ("sim", "exposure"): 0.0,
    ("sim", "white_balance"): [1.0, 6.0, 1.0],
    ("sim", "gain_noise"): 0.6,
    ("sim", "vignetting"): 1.5,
    ("sim", "motion_blur"): 0.5,
    ("randomize", "appearance"): None,  # true or false
    ("randomize", "floor_families"): ["wood", "marble"],
    ("randomize", "heldout_floor_hsv"): [28.0, 40.0, 0.4],
    ("randomize", "floor_saturation"): [0.5, 1.5],
    ("randomize", "floor_value"): [0.9, 0.1],
    ("randomize", "wall_textures"): ["brick"],
    ("randomize", "home_walls"): 1.5,
    ("randomize", "skirting"): -0.1,
    ("randomize", "clutter"): [0, 13],
    ("randomize", "lamps"): [3, 1],
    ("randomize", "window_light"): [0.0, 3.0],
    ("randomize", "light_temperature"): [500.0, 6500.0],
    ("randomize", "shadows"): 2.0,
    ("randomize", "exposure"): [0.01, 1.0],
    ("randomize", "white_balance"): [0.1, 1.0],
    ("randomize", "gain_noise"): [0.0, 0.6],
    ("randomize", "vignetting"): [0.5, 0.2],
    ("randomize", "motion_blur"): [0.0, 0.3],
}
# Every duration and rate is bounded at both ends (unbounded, a 1e-10 Hz rate would crash
# the loop thread, a 1e10 s timeout the watchdog's wait); TOML's inf and nan too.
MORE_OUT_OF_RANGE = [
    ("loop", "rate_hz", 1e-10), ("loop", "rate_hz", 1000.0), ("loop", "rate_hz", "inf"),
    ("loop", "max_frame_age", 1e10), ("loop", "watchdog_timeout", 1e10),
    ("loop", "watchdog_timeout", "nan"), ("loop", "warmup_timeout", 1e10),
    ("loop", "warmup_timeout", "inf"), ("camera", "fps", 1e6), ("camera", "start_timeout", 1e10),
    ("sim", "physics_hz", 1e12), ("sim", "motor_tau", "inf"), ("sim", "camera_stall_after", 1e12),
    ("camera", "source", 'gst:videotestsrc ! capsfilter caps="video/x-raw'),
    ("camera", "source", "gst:videotestsrc ! textoverlay text='unbalanced"),
]
# A value of the wrong TOML type for each declared type.
WRONG_TYPE = {"bool": "yes", "float": "fast", "int": 1.5, "str": 7, "list[float]": 0.5,
              "list[int]": "both", "list[str]": "CPUExecutionProvider"}


def all_keys() -> list[tuple[str, str, str]]:
    keys = []
    for section in dataclasses.fields(Config):
        types = schema.key_types(type(section.default_factory()))
        for key in dataclasses.fields(section.default_factory()):
            keys.append((section.name, key.name, schema.type_name(types[key.name])))
    return keys


def test_the_table_names_every_config_key() -> None:
    """A key added to the config sections without a bad-value case here fails this test."""
    assert {(s, k) for s, k, _ in all_keys()} == set(OUT_OF_RANGE)


def toml_value(value: object) -> str:
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, list):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    return repr(value)


def config_cases():
    for section, key, type_name in all_keys():
        yield pytest.param(f"[{section}]\n{key} = {toml_value(WRONG_TYPE[type_name])}\n",
                           f"[{section}] {key} must be", id=f"{section}.{key}-wrong-type")
        bad = OUT_OF_RANGE[(section, key)]
        if bad is not None:
            yield pytest.param(f"[{section}]\n{key} = {toml_value(bad)}\n",
                               f"[{section}] {key} must be", id=f"{section}.{key}-out-of-range")
        yield pytest.param(f"[{section}]\n{key}s = 1\n", f"unknown key [{section}] {key}s",
                           id=f"{section}.{key}s-unknown")
    for section, key, bad in MORE_OUT_OF_RANGE:
        value = bad if bad in ("inf", "nan") else json.dumps(bad)
        yield pytest.param(f"[{section}]\n{key} = {value}\n", f"[{section}] {key} must be",
                           id=f"{section}.{key}-{str(bad)[:12]}")
    yield pytest.param("[wheels]\nleft = 1\n", "unknown section [wheels]", id="unknown-section")
    yield pytest.param("loop = 30\n", "[loop] must be a table", id="section-not-a-table")
    yield pytest.param("[loop\nrate_hz = 30\n", "is not valid TOML", id="not-toml")
    yield pytest.param("[loop]\nrate_hz = 30\nrate_hz = 20\n", "is not valid TOML",
                       id="duplicate-key")


@pytest.fixture
def good_policy(tmp_path_factory) -> Path:
    return policy_models.constant(tmp_path_factory.mktemp("policy") / "good.onnx")


def run_in_process(args: list[str], capfd) -> tuple[int, list[str]]:
    """The CLI's own entry point, in this process: a config error ends before any backend
    exists. ``--duration`` keeps a wrongly accepted config from driving for long (first: a
    later ``--duration`` in ``args`` wins)."""
    code = main([args[0], "--duration", "0.2", *args[1:]])
    return code, capfd.readouterr().err.strip().splitlines()


@pytest.mark.parametrize(("text", "message"), list(config_cases()))
def test_every_bad_config_key_and_value(tmp_path, good_policy, capfd, monkeypatch,
                                        text, message) -> None:
    monkeypatch.setenv("JETBOT_RT_RUNTIME_DIR", str(tmp_path / "run"))
    path = tmp_path / "bad.toml"
    path.write_text(text)
    code, lines = run_in_process(["run", "--backend", "sim", "--policy", str(good_policy),
                                  "--config", str(path)], capfd)
    assert code == 2
    assert len(lines) == 1 and message in lines[0], lines
    assert str(path) in lines[0]  # which file


@pytest.mark.parametrize(("flags", "message"), [
    (["--rate", "inf"], "--rate: [loop] rate_hz must be a number in [1, 100] Hz"),
    (["--rate", "nan"], "--rate: [loop] rate_hz must be a number in [1, 100] Hz"),
    (["--rate", "-30"], "--rate: [loop] rate_hz must be a number in [1, 100] Hz"),
    (["--max-speed", "0"], "--max-speed: [actions] max_speed must be a number in (0, 1]"),
    (["--max-speed", "nan"], "--max-speed: [actions] max_speed must be a number in (0, 1]"),
    (["--duration", "0"], "--duration must be > 0"),
    (["--duration", "nan"], "--duration must be > 0"),
    (["--telemetry", "/nonexistent-dir/t.jsonl"], "cannot write telemetry"),
    (["--telemetry", "/"], "cannot write telemetry /"),
])
def test_bad_and_conflicting_flags(tmp_path, good_policy, capfd, monkeypatch, flags,
                                   message) -> None:
    monkeypatch.setenv("JETBOT_RT_RUNTIME_DIR", str(tmp_path / "run"))
    code, lines = run_in_process(["run", "--backend", "sim", "--policy", str(good_policy),
                                  *flags], capfd)
    assert code == 2
    assert len(lines) == 1 and message in lines[0], lines


def model_cases(tmp_path: Path) -> list:
    good = policy_models.constant(tmp_path / "good.onnx")
    truncated = tmp_path / "truncated.onnx"
    truncated.write_bytes(good.read_bytes()[: len(good.read_bytes()) // 2])
    empty = tmp_path / "empty.onnx"
    empty.write_bytes(b"")
    a_config = tmp_path / "config.toml"
    a_config.write_text("[loop]\nrate_hz = 30\n")
    bad_meta = policy_models.constant(tmp_path / "bad_meta.onnx",
                                      metadata={"jetbot_rt.color_order": "YUV"})
    return [
        ("empty", empty, "not a loadable ONNX model"),
        ("truncated", truncated, "not a loadable ONNX model"),
        ("a-toml-file", a_config, "not a loadable ONNX model"),
        ("a-directory", tmp_path, "a directory"),
        ("unknown-operator", policy_models.unknown_operator(tmp_path / "op.onnx"),
         "is not a registered function/op"),
        ("dynamic-size", policy_models.dynamic_size(tmp_path / "dyn.onnx"), "has no fixed size"),
        ("two-inputs", policy_models.two_inputs(tmp_path / "two.onnx"),
         "expected one image input, found 2"),
        ("int-actions", policy_models.int_output(tmp_path / "int.onnx"),
         "expected float actions in output mu"),
        ("bad-metadata", bad_meta, "unsupported metadata color_order='YUV'"),
    ]


MODEL_IDS = ["empty", "truncated", "a-toml-file", "a-directory", "unknown-operator",
             "dynamic-size", "two-inputs", "int-actions", "bad-metadata"]


@pytest.mark.parametrize("case", MODEL_IDS)
def test_broken_models_are_refused_before_any_motor_command(tmp_path, case) -> None:
    (path, message), = [(p, m) for name, p, m in model_cases(tmp_path) if name == case]
    telemetry = tmp_path / "t.jsonl"
    result = run_cli(["run", "--backend", "sim", "--policy", str(path), "--duration", "1"],
                     telemetry=telemetry,
                     env=dict(os.environ, JETBOT_RT_RUNTIME_DIR=str(tmp_path / "run")))
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], lines
    assert "Traceback" not in result.stderr
    assert not result.ticks
    (end,) = result.records
    assert end["event"] == "end" and end["exit_code"] == 2 and end["cmd"] == [0.0, 0.0]


@pytest.mark.slow
@pytest.mark.skipif(sim_problem() is not None, reason=str(sim_problem()))
def test_a_policy_that_hangs_on_its_first_frame_is_refused_at_warm_up(tmp_path) -> None:
    """The warm-up runs in a thread with a time limit ([loop] warmup_timeout): a model that
    never returns is a usage error, and the process ends although that thread cannot."""
    policy = policy_models.hang_when_dark(tmp_path / "hang.onnx")
    config = "[sim]\nblackout = [0.0, 1000.0]\n[loop]\nwarmup_timeout = 1.0\n"
    rt = RuntimeProcess(tmp_path, "sim", policy, config=config, duration=5.0)
    try:
        result = rt.start().finish(60)
    finally:
        rt.kill()
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "warm-up inference did not finish within 1.0 s" in lines[0]
    assert not result.ticks


CAMERA_CASES = [
    ("no-such-element", "nosuchsrc name={mark}", 'no element "nosuchsrc"'),
    ("bad-property", "videotestsrc name={mark} pattern=nosuch", 'could not set property'),
    ("cannot-link", "videotestsrc name={mark} ! jpegenc", "could not link jpegenc"),
    ("ends-before-first-frame", "videotestsrc name={mark} num-buffers=0",
     "camera pipeline ended before its first frame"),
    ("no-frame-in-time", "videotestsrc name={mark} is-live=true ! valve drop=true",
     "camera gave no frame within 1 s"),
]


@pytest.mark.skipif(shutil.which("gst-launch-1.0") is None, reason="needs gst-launch-1.0")
@pytest.mark.parametrize(("source", "message"), [pytest.param(s, m, id=i)
                                                 for i, s, m in CAMERA_CASES])
def test_a_camera_that_cannot_start_is_exit_2_with_the_board_off(tmp_path, source,
                                                                  message) -> None:
    mark = f"fm{uuid.uuid4().hex[:12]}"
    policy = policy_models.constant(tmp_path / "policy.onnx")
    config = f'[camera]\nsource = "gst:{source.format(mark=mark)}"\nstart_timeout = 1\n'
    rt = RuntimeProcess(tmp_path, "real", policy, config=config, duration=5.0)
    try:
        result = rt.start().finish(60)
    finally:
        rt.kill()
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], lines
    assert not result.ticks
    assert rt.board_off()
    assert wait_for(lambda: not processes_with(mark), 3.0) is not None


@pytest.mark.skipif(shutil.which("gst-launch-1.0") is None, reason="needs gst-launch-1.0")
def test_a_second_runtime_is_refused_before_it_touches_the_board(tmp_path) -> None:
    """Two services on one robot: the second is exit 2, naming the first (the owner of the
    bus), and the first drives on (tests/test_fault_ownership.py varies this)."""
    mark = f"fm{uuid.uuid4().hex[:12]}"
    policy = policy_models.constant(tmp_path / "policy.onnx", (1.0, 1.0))
    first = RuntimeProcess(tmp_path, "real", policy, duration=30.0,
                           config=f'[camera]\nsource = "gst:videotestsrc name={mark} '
                                  'is-live=true"\nstart_timeout = 10\n'
                                  # patient: a loaded host's stale frame is not this case
                                  '[loop]\nwatchdog_timeout = 1.0\nmax_frame_age = 1.0\n')
    try:
        first.start()
        first.wait_ticks(10)
        result = run_cli(first.board(["run", "--backend", "real", "--policy", str(policy),
                                      "--config", str(first.config)]), env=first.env,
                         timeout=60)
        assert result.returncode == 2, result.stderr
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and f"is driven by pid {first.pid}" in lines[0], lines
        before = first.tick_count()
        first.wait_ticks(before + 10)  # the first drives on
        assert not first.board_off()
        first.jetbot_rt("stop")
        ended = first.finish(30)
    finally:
        first.kill()
    assert ended.returncode == 0 and first.board_off()

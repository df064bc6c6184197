"""Seeded fuzzing of every reader of a file we did not write: recordings (``meta.json``,
``ticks.jsonl``, ``summary.json``, through replay's and report's own use of them), configs
(``config.load_config``, through ``safe_file``) and policies' metadata (``OnnxPolicy.load``).

Each starts from a valid file and mutates it: byte flips, truncation, inserted bytes, deleted
keys, swapped types, huge numbers, NaN and Infinity, deep nesting, lone surrogates. The
promise checked on every case: either it is read (and then used without error) or it is one
``UsageError`` of one line, which the command line turns into exit 2; nothing else escapes, no
case hangs, and nothing is written outside the output directory. In-process for speed (each
loop stops after ``BUDGET_S``), plus a few cases end to end through ``jetbot-rt``.
"""

from __future__ import annotations

import json
import math
import os
import random
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import onnx
import policy_models
import pytest
from recording_fixtures import jetbot_rt, make_recording

from jetbot_rt.commands import replay, report
from jetbot_rt.config.sections import load_config
from jetbot_rt.errors import UsageError
from jetbot_rt.recording.reader import Recording
from jetbot_rt.runtime.policy import OnnxPolicy, bundled_policy_path

BUDGET_S = float(os.environ.get("JETBOT_RT_FUZZ_S", "2"))
"""Each fuzz loop runs its seeded cases until this much time has passed (at least a few);
``JETBOT_RT_FUZZ_S=600`` searches longer."""
CASE_HANG_S = 30.0
"""One case taking longer than this is a hang (a case takes milliseconds)."""

HOSTILE_VALUES: list[Any] = [
    None, True, False, "", "x" * 5000, "\udcff", -1, 0, 1, 2**70, -(2**70), 1e308, -1e308,
    1e-320, 0.5, math.nan, math.inf, -math.inf, [], {}, [1, 2, 3], [math.nan, 1.0],
    {"a": {"b": [None]}}, [[[[[[[[[[1]]]]]]]]]], "../../etc/passwd", "/dev/zero",
]


def _paths(value: Any, prefix: tuple = ()) -> list[tuple]:
    """Every (nested) key or index in ``value``."""
    found = []
    if isinstance(value, dict):
        items: Any = value.items()
    elif isinstance(value, list):
        items = enumerate(value)
    else:
        return found
    for key, item in items:
        found.append((*prefix, key))
        found.extend(_paths(item, (*prefix, key)))
    return found


def mutate_value(rng: random.Random, doc: Any) -> Any:
    """The document with one key deleted, or one value swapped for a hostile one."""
    paths = _paths(doc)
    if not paths:
        return rng.choice(HOSTILE_VALUES)
    path = rng.choice(paths)
    parent = doc
    for key in path[:-1]:
        parent = parent[key]
    if isinstance(parent, dict) and rng.random() < 0.3:
        del parent[path[-1]]
    else:
        parent[path[-1]] = rng.choice(HOSTILE_VALUES)
    return doc


def dump(doc: Any) -> bytes:
    """JSON as Python writes it: NaN and Infinity as tokens, surrogates as escapes."""
    return json.dumps(doc).encode()


def mutate_bytes(rng: random.Random, data: bytes) -> bytes:
    choice = rng.randrange(6)
    position = rng.randrange(len(data) + 1)
    if choice == 0 and data:  # flip bytes
        array = bytearray(data)
        for _ in range(rng.randint(1, 8)):
            array[rng.randrange(len(array))] = rng.randrange(256)
        return bytes(array)
    if choice == 1:  # truncate
        return data[:position]
    if choice == 2:  # insert random bytes
        return data[:position] + bytes(rng.randrange(256) for _ in range(rng.randint(1, 16))) \
            + data[position:]
    if choice == 3:  # deep nesting
        depth = rng.choice([100, 10_000, 200_000])
        return data[:position] + b"[" * depth + b"]" * depth + data[position:]
    if choice == 4:  # a huge number literal
        return data[:position] + b"9" * rng.choice([30, 5000, 100_000]) + data[position:]
    return data[:position] + rng.choice([b"NaN", b"Infinity", b"-Infinity", b"1e999", b"\\udcff",
                                         b"\x00", b"\xff\xfe", b"\n"]) + data[position:]


def mutate_document(rng: random.Random, data: bytes) -> bytes:
    if rng.random() < 0.5:
        return dump(mutate_value(rng, json.loads(data)))
    return mutate_bytes(rng, data)


def mutate_jsonl(rng: random.Random, data: bytes) -> bytes:
    lines = data.split(b"\n")[:-1]
    index = rng.randrange(len(lines))
    roll = rng.random()
    if roll < 0.1:  # lines swapped: time and frames out of order
        other = rng.randrange(len(lines))
        lines[index], lines[other] = lines[other], lines[index]
    elif roll < 0.15:
        return mutate_bytes(rng, data)  # anywhere, the newline structure included
    else:
        lines[index] = mutate_document(rng, lines[index])
    return b"".join(line + b"\n" for line in lines)


def within_promise(case: str, action: Callable[[], Any], max_length: int = 600) -> str:
    """Run ``action``: ``ok``, or ``refused`` for one ``UsageError`` of one line (of at most
    ``max_length`` characters). Anything else fails the test, naming the case."""
    start = time.monotonic()
    try:
        action()
        outcome = "ok"
    except UsageError as exc:
        text = str(exc)
        assert text and "\n" not in text and len(text) <= max_length, (case, text[:2000])
        text.encode("utf-8")  # printable on a strict stream
        outcome = "refused"
    assert time.monotonic() - start < CASE_HANG_S, f"{case}: took {time.monotonic() - start} s"
    return outcome


def snapshot(root: Path, skip: Path) -> dict[str, tuple[int, int]]:
    return {str(p): (p.stat().st_size, p.stat().st_mtime_ns) for p in root.rglob("*")
            if p.is_file() and skip not in p.parents}


@pytest.fixture(scope="module")
def pristine(tmp_path_factory) -> Path:
    return make_recording(tmp_path_factory.mktemp("fuzz") / "rec", ticks=8)


@pytest.fixture(scope="module")
def bundled() -> OnnxPolicy:
    return OnnxPolicy.load(bundled_policy_path())


def use_recording(path: Path, out: Path, policy: OnnxPolicy) -> None:
    """Everything replay and report do with a recording, in-process (no plot: matplotlib
    takes a second a figure, and it only sees numbers validated already)."""
    recording = Recording.open(path)
    replay.policy_config(recording)
    replay.replay(recording, policy, 1e-4)
    if recording.ticks:
        report.summarize(recording)
        report.Video(recording).write(out, "run.mp4")


@pytest.mark.parametrize("target", ["meta.json", "ticks.jsonl", "summary.json"])
def test_fuzzed_recordings_are_read_or_refused_in_one_line(pristine, bundled, tmp_path, target):
    rng = random.Random(f"recording-{target}")
    mutate = mutate_jsonl if target == "ticks.jsonl" else mutate_document
    original = (pristine / target).read_bytes()
    outcomes = {"ok": 0, "refused": 0}
    deadline = time.monotonic() + BUDGET_S
    case = 0
    while case < 20 or time.monotonic() < deadline:
        case += 1
        rec = tmp_path / f"case-{case}"
        shutil.copytree(pristine, rec)
        (rec / target).write_bytes(mutate(rng, original))
        out = tmp_path / f"out-{case}"
        out.mkdir()
        before = snapshot(tmp_path, out)
        outcomes[within_promise(f"{target} case {case}",
                                lambda rec=rec, out=out: use_recording(rec, out, bundled))] += 1
        assert snapshot(tmp_path, out) == before, f"{target} case {case} wrote outside --out"
        shutil.rmtree(rec)
        shutil.rmtree(out)
    assert outcomes["refused"] > 0 and sum(outcomes.values()) >= 20, outcomes


@pytest.mark.parametrize("seed", [1, 2])
def test_fuzzed_recordings_end_to_end_exit_0_or_2_with_one_line(pristine, tmp_path, seed):
    rng = random.Random(f"end-to-end-{seed}")
    rec = Path(shutil.copytree(pristine, tmp_path / "rec"))
    for target in ("meta.json", "ticks.jsonl"):
        mutate = mutate_jsonl if target == "ticks.jsonl" else mutate_document
        (rec / target).write_bytes(mutate(rng, (rec / target).read_bytes()))
    for command in ("report", "replay"):
        before = snapshot(tmp_path, tmp_path / "out")
        proc = jetbot_rt(command, str(rec), *(["--out", str(tmp_path / "out")]
                                             if command == "report" else []), timeout=60)
        assert proc.returncode in (0, 2), proc.stderr[-2000:]
        assert "Traceback" not in proc.stderr, proc.stderr[-2000:]
        if proc.returncode == 2:
            assert proc.stderr.count("\n") == 1, proc.stderr
        assert snapshot(tmp_path, tmp_path / "out") == before


VALID_CONFIG = b"""# a robot's config
[loop]
rate_hz = 30.0
watchdog_timeout = 0.5

[motors]
i2c_bus = 1
layout = "waveshare"

[policy]
threads = 1
layout = "NHWC"

[camera]
source = "csi"
fps = 30

[actions]
max_speed = 0.2
trim = [1.0, 0.95]
"""


def mutate_toml(rng: random.Random, data: bytes) -> bytes:
    if rng.random() < 0.5:
        return mutate_bytes(rng, data)
    lines = data.split(b"\n")
    index = rng.randrange(len(lines))
    if b"=" in lines[index]:
        key = lines[index].split(b"=")[0]
        value = rng.choice([b"nan", b"inf", b"-inf", b"1e400", b"9" * 5000, b'"x"', b"[]",
                            b"{}", b"true", b"0", b"-1", b'"\\udcff"', b"[" * 5000,
                            b"1979-05-27T07:32:00Z", b'"' + b"y" * 10_000 + b'"'])
        lines[index] = key + b"= " + value
    else:
        lines[index] = rng.choice([b"[loop.x]", b"[[loop]]", b"[unknown]", b"x = 1",
                                   b"\xff\xfe", b"[loop]"])
    return b"\n".join(lines)


def test_fuzzed_configs_load_or_are_refused_in_one_line(tmp_path):
    rng = random.Random("config")
    (tmp_path / "valid.toml").write_bytes(VALID_CONFIG)
    load_config(tmp_path / "valid.toml")  # the starting point is valid
    outcomes = {"ok": 0, "refused": 0}
    deadline = time.monotonic() + BUDGET_S
    case = 0
    while case < 50 or time.monotonic() < deadline:
        case += 1
        path = tmp_path / "c.toml"
        path.write_bytes(mutate_toml(rng, VALID_CONFIG))
        # the config reader quotes a bad value whole: one line, as long as the value (at most the
        # file's 256 KiB)
        outcomes[within_promise(f"config case {case}", lambda path=path: load_config(path),
                                max_length=300_000)] += 1
    assert outcomes["refused"] > 0 and outcomes["ok"] > 0, outcomes


METADATA = {"jetbot_rt.max_speed": "0.1", "jetbot_rt.layout": "NHWC",
            "jetbot_rt.color_order": "RGB", "jetbot_rt.pixel_range": "0-255",
            "jetbot_rt.input_size": "16x16", "jetbot_rt.task": "forward"}


def test_fuzzed_policy_metadata_loads_or_is_refused_in_one_line(tmp_path):
    rng = random.Random("policy-metadata")
    strings = ["", "nan", "inf", "-0", "1e-400", "1e400", "9" * 5000, "NCHW", "BGR", "0-1",
               "-1-1", "16x16", "17x16", "0x0", "x", "\x00", "é", "2147483648x2147483648",
               "0.5", "1", "1.5", " 0.1", "0.1 "]
    outcomes = {"ok": 0, "refused": 0}
    deadline = time.monotonic() + BUDGET_S
    case = 0
    while case < 30 or time.monotonic() < deadline:
        case += 1
        metadata = dict(METADATA)
        for _ in range(rng.randint(1, 3)):
            key = rng.choice([*METADATA, "jetbot_rt.other", ""])
            if rng.random() < 0.2:
                metadata.pop(key, None)
            else:
                metadata[key] = rng.choice(strings)
        path = policy_models.constant(tmp_path / "p.onnx", size=16, metadata=metadata)
        outcomes[within_promise(f"metadata {metadata}",
                                lambda path=path: OnnxPolicy.load(path))] += 1
    assert outcomes["refused"] > 0 and outcomes["ok"] > 0, outcomes


def test_byte_flipped_policies_are_refused_in_one_line_end_to_end(tmp_path):
    """Byte flips reach onnxruntime's own parser: in a child process (a crash there would be
    onnxruntime's, and must not take the test run with it), through ``jetbot-rt replay``."""
    rng = random.Random("policy-bytes")
    rec = make_recording(tmp_path / "rec", ticks=2)
    valid = policy_models.constant(tmp_path / "valid.onnx", size=56, metadata=METADATA | {
        "jetbot_rt.input_size": "56x56"})
    data = valid.read_bytes()
    model = onnx.load(str(valid))
    assert model.graph.input[0].name == "obs"
    for case in range(4):
        flipped = bytearray(data)
        for _ in range(rng.randint(1, 6)):
            flipped[rng.randrange(len(flipped))] = rng.randrange(256)
        path = tmp_path / f"flipped-{case}.onnx"
        path.write_bytes(bytes(flipped))
        proc = jetbot_rt("replay", str(rec), "--policy", str(path), "--json", timeout=60)
        assert proc.returncode in (0, 2), (case, proc.returncode, proc.stderr[-2000:])
        assert "Traceback" not in proc.stderr, proc.stderr[-2000:]
        if proc.returncode == 2:
            assert proc.stderr.count("\n") == 1, proc.stderr

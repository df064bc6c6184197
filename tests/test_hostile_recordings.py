"""Recordings are untrusted input: replay and report read every file of one through
``safe_file`` and validate every record once; whatever is wrong is one line on stderr and
exit 2, never a traceback, a hang, memory or disk without end, or a write through a planted
link. Each example the adversarial review found is here as a regression test, end to end
through the ``jetbot-rt`` console script, and the classes behind them in-process (fast).
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import resource
import shutil
import tracemalloc
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
from recording_fixtures import (
    TICKS,
    assert_refused,
    jetbot_rt,
    make_recording,
    read_lines,
    write_lines,
)

from jetbot_rt.commands import report
from jetbot_rt.errors import UsageError
from jetbot_rt.recording import reader
from jetbot_rt.recording.reader import LINE_BYTES, TICKS_BYTES, Recording

HANG_S = 60.0
"""A case that takes longer hangs: each is one interpreter start and a few ms of work."""


@pytest.fixture(scope="module")
def pristine(tmp_path_factory) -> Path:
    return make_recording(tmp_path_factory.mktemp("pristine") / "rec")


@pytest.fixture
def rec(pristine, tmp_path) -> Path:
    """A fresh copy of the valid recording, to spoil."""
    return Path(shutil.copytree(pristine, tmp_path / "rec"))


def edit_meta(change: Callable[[dict], object]) -> Callable[[Path], None]:
    def spoil(path: Path) -> None:
        meta = json.loads((path / "meta.json").read_text())
        result = change(meta)
        (path / "meta.json").write_text(json.dumps(meta if result is None else result))
    return spoil


def edit_tick(index: int, change: Callable[[dict], object]) -> Callable[[Path], None]:
    def spoil(path: Path) -> None:
        records = read_lines(path)
        result = change(records[index])
        if result is not None:
            records[index] = result
        write_lines(path, records)
    return spoil


def raw(name: str, data: bytes) -> Callable[[Path], None]:
    def spoil(path: Path) -> None:
        (path / name).write_bytes(data)
    return spoil


def replace_text(name: str, old: str, new: str) -> Callable[[Path], None]:
    def spoil(path: Path) -> None:
        text = (path / name).read_text()
        assert old in text
        (path / name).write_text(text.replace(old, new, 1))
    return spoil


def fifo(name: str) -> Callable[[Path], None]:
    def spoil(path: Path) -> None:
        (path / name).unlink()
        os.mkfifo(path / name)
    return spoil


def link(name: str, target: str) -> Callable[[Path], None]:
    def spoil(path: Path) -> None:
        (path / name).unlink()
        (path / name).symlink_to(target)
    return spoil


def pop(key: str) -> Callable[[dict], None]:
    return lambda record: record.__delitem__(key)


def put(key: str, value: object) -> Callable[[dict], None]:
    return lambda record: record.__setitem__(key, value)


MALFORMED: dict[str, tuple[Callable[[Path], None], str]] = {
    # meta.json
    "meta-a-list": (edit_meta(lambda m: [m]), "must be a JSON object, got list"),
    "meta-no-format": (edit_meta(pop("format")), "recording format 'None'"),
    "meta-version-3": (edit_meta(put("version", 3)), "version '3'"),
    "rate-hz-0": (edit_meta(put("rate_hz", 0)), "rate_hz must be within [0.1, 1000], got 0"),
    "rate-hz-text": (edit_meta(put("rate_hz", "30")), "rate_hz must be a number, got str"),
    "rate-hz-missing": (edit_meta(pop("rate_hz")), "rate_hz must be a number, got nothing"),
    "rate-hz-1e400": (replace_text("meta.json", '"rate_hz": 30.0', '"rate_hz": 1e400'),
                      "rate_hz must be within"),
    "rate-hz-nan": (replace_text("meta.json", '"rate_hz": 30.0', '"rate_hz": NaN'),
                    "NaN is not a number"),
    "frame-size-missing": (edit_meta(pop("frame_size")), "frame_size must be [width, height]"),
    "frame-size-zero": (edit_meta(put("frame_size", [0, 56])), "frame_size[0] must be within"),
    "frame-size-huge": (edit_meta(put("frame_size", [20000, 20000])),
                        "frame_size[0] must be within [1, 4096]"),
    "frame-size-text": (edit_meta(put("frame_size", ["56", 56])),
                        "frame_size[0] must be an integer"),
    "frames-parent": (edit_meta(put("frames", "../../etc/passwd")), "frames must be a file name"),
    "frames-absolute": (edit_meta(put("frames", "/dev/zero")), "frames must be a file name"),
    "max-speed-negative": (edit_meta(put("max_speed", -1)), "max_speed must be within"),
    "policy-a-string": (edit_meta(put("policy", "x.onnx")), "policy must be an object"),
    "policy-path-a-number": (edit_meta(lambda m: m["policy"].__setitem__("path", 5)),
                             "path must be text"),
    "config-a-list": (edit_meta(put("config", [])), "config must be an object"),
    "config-policy-a-list": (edit_meta(put("config", {"policy": [1]})),
                             "config.policy must be an object"),
    "meta-not-utf8": (raw("meta.json", b'{"format": "\xff"}'), "is not UTF-8: byte 0xff"),
    "meta-truncated": (raw("meta.json", b'{"format": "jetbot_rt.rec'), "is not valid JSON"),
    "meta-empty": (raw("meta.json", b""), "is not valid JSON"),
    "meta-nested": (raw("meta.json", b"[" * 100_000 + b"]" * 100_000), "nested too deeply"),
    "meta-lone-surrogate": (edit_meta(put("backend", "\udcff")), "lone surrogate"),
    "meta-huge-integer": (raw("meta.json", b'{"rate_hz": ' + b"9" * 100_000 + b"}"),
                          "an integer of 100000 digits"),
    "meta-a-directory": (lambda p: ((p / "meta.json").unlink(), (p / "meta.json").mkdir()),
                         "meta.json: a directory"),
    "meta-missing": (lambda p: (p / "meta.json").unlink(), "is not a recording (no meta.json)"),
    # ticks.jsonl
    "tick-a-list": (edit_tick(3, lambda r: [r]), "line 4: a record must be a JSON object"),
    "tick-no-t": (edit_tick(3, pop("t")), "line 4: t must be a number, got nothing"),
    "tick-t-text": (edit_tick(3, put("t", "0.1")), "line 4: t must be a number, got str"),
    "tick-t-negative": (edit_tick(0, put("t", -1.0)), "line 1: t must be within"),
    "tick-t-goes-back": (edit_tick(5, put("t", 0.0)), "line 6: t goes back"),
    "tick-repeated": (edit_tick(5, put("tick", 5)), "line 6: tick 5 after tick 5"),
    "tick-a-bool": (edit_tick(0, put("tick", True)), "line 1: tick must be an integer"),
    "mu-missing": (edit_tick(2, pop("mu")), "line 3: mu must be a list of two numbers"),
    "mu-one-value": (edit_tick(2, put("mu", [1.0])), "mu must be a list of two numbers"),
    "mu-text": (edit_tick(2, put("mu", ["a", 1.0])), "mu[0] must be a number, got str"),
    "cmd-beyond-1": (edit_tick(2, put("cmd", [2.0, 0.0])), "cmd[0] must be within [-1, 1]"),
    "frame-infinity": (edit_tick(4, put("frame", float("inf"))),
                       "line 5: not a JSON record (Infinity is not a number"),
    "frame-float": (edit_tick(4, put("frame", 1e308)), "line 5: frame must be an integer"),
    "frame-past-its-tick": (edit_tick(0, put("frame", 5)), "line 1: frame must be within [0, 0]"),
    "frame-goes-back": (edit_tick(6, put("frame", 2)), "line 7: frame 2 after frame 5"),
    "overruns-negative": (edit_tick(1, put("overruns", -1)), "overruns must be within"),
    "tick-ms-text": (edit_tick(1, put("tick_ms", "fast")), "tick_ms must be a number"),
    "neither-tick-nor-event": (edit_tick(1, lambda r: {"x": 1}), "neither a tick record"),
    "event-without-t": (edit_tick(TICKS, pop("t")), "t must be a number, got nothing"),
    "event-fault-text": (edit_tick(TICKS, put("fault", "yes")), "fault must be true or false"),
    "event-name-a-number": (edit_tick(TICKS, put("event", 5)), "event must be text"),
    "garbage-line-in-the-middle": (replace_text("ticks.jsonl", "\n", "\n}{garbage\n"),
                                   "line 2: not a JSON record"),
    "ticks-not-utf8": (lambda p: (p / "ticks.jsonl").write_bytes(
        (p / "ticks.jsonl").read_bytes().replace(b"\n", b'\n{"t": "\xff"}\n', 1)),
        "line 2: not a JSON record (not UTF-8: byte 0xff)"),
    "ticks-missing": (lambda p: (p / "ticks.jsonl").unlink(), "No such file or directory"),
    "ticks-larger-than-the-cap": (lambda p: os.truncate(p / "ticks.jsonl", TICKS_BYTES + 1),
                                  "is larger than 128 MiB"),
    "a-line-longer-than-the-cap": (raw("ticks.jsonl", b'{"x": "' + b"y" * LINE_BYTES + b'"}\n'),
                                   "line 1: longer than 1 MiB"),
    # summary.json
    "summary-a-list": (raw("summary.json", b"[]"), "summary.json: must be a JSON object"),
    "summary-negative-count": (raw("summary.json", b'{"frames_written": -1}'),
                               "frames_written must be within"),
    "summary-error-a-number": (raw("summary.json", b'{"error": 5}'), "error must be text"),
    # files that are not what they say
    "meta-a-fifo": (fifo("meta.json"), "meta.json: not a regular file"),
    "ticks-a-fifo": (fifo("ticks.jsonl"), "ticks.jsonl: not a regular file"),
    "summary-a-fifo": (fifo("summary.json"), "summary.json: not a regular file"),
    "meta-a-link-to-dev-zero": (link("meta.json", "/dev/zero"), "meta.json: a symbolic link"),
    "ticks-a-link-to-dev-zero": (link("ticks.jsonl", "/dev/zero"), "a symbolic link"),
    "ticks-a-link-to-a-good-file": (link("ticks.jsonl", "/etc/hostname"), "a symbolic link"),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_a_malformed_recording_is_one_usage_error_naming_the_problem(rec, case):
    spoil, message = MALFORMED[case]
    spoil(rec)
    with pytest.raises(UsageError) as info:
        recording = Recording.open(rec)
        list(recording.ticks_with_frames())
    text = str(info.value)
    assert message in text and "\n" not in text and len(text) < 400, text


VIDEO_SPOILS = {
    "frames-a-fifo": (fifo("frames.mkv"), "frames.mkv: not a regular file"),
    "frames-a-link": (link("frames.mkv", "/dev/zero"), "frames.mkv: a symbolic link"),
    "frames-of-another-size": (None, "holds 16x8 frames, meta.json says 56x56"),
}


@pytest.mark.parametrize("case", sorted(VIDEO_SPOILS))
def test_a_video_that_is_not_the_recordings_is_refused_when_read(rec, case):
    spoil, message = VIDEO_SPOILS[case]
    if spoil is None:  # a valid video of frames of another size
        (rec / "frames.mkv").unlink()
        writer = cv2.VideoWriter(str(rec / "frames.mkv"), cv2.VideoWriter_fourcc(*"HFYU"), 30,
                                 (16, 8))
        for _ in range(3):
            writer.write(np.zeros((8, 16, 3), np.uint8))
        writer.release()
    else:
        spoil(rec)
    recording = Recording.open(rec)
    with pytest.raises(UsageError, match=message):
        list(recording.ticks_with_frames())


def test_what_a_run_cut_short_leaves_is_read_as_far_as_it_goes(rec):
    """A half-written last line is skipped; without the video every tick has no frame."""
    text = (rec / "ticks.jsonl").read_text()
    (rec / "ticks.jsonl").write_text(text[: text.rindex("\n", 0, len(text) - 1) + 20])
    (rec / "frames.mkv").unlink()
    (rec / "summary.json").unlink()
    recording = Recording.open(rec)
    assert len(recording.ticks) == TICKS and recording.summary == {}
    assert [image for _, image in recording.ticks_with_frames()] == [None] * TICKS


def test_the_pristine_recording_reads_whole(rec):
    recording = Recording.open(rec)
    frames = [image for _, image in recording.ticks_with_frames()]
    assert len(frames) == TICKS and all(f is not None and f.shape == (56, 56, 3) for f in frames)
    assert [e["event"] for e in recording.events] == ["safe_stop", "end"]
    assert recording.summary["frames_written"] == TICKS


# ---- the review's examples, end to end --------------------------------------------------


def test_a_frame_of_infinity_is_refused_by_replay_and_report_instead_of_spinning(rec):
    edit_tick(4, put("frame", float("inf")))(rec)
    for command in ("replay", "report"):
        proc = jetbot_rt(command, str(rec), timeout=HANG_S)
        assert_refused(proc, "ticks.jsonl line 5: not a JSON record")
    assert not (rec / "run.png").exists()


def test_a_last_t_far_in_the_future_makes_a_bounded_video(rec):
    edit_tick(TICKS - 1, put("t", 1e8))(rec)
    proc = jetbot_rt("report", str(rec), timeout=HANG_S)
    assert proc.returncode == 0, proc.stderr
    assert "1 pauses over 10 s shortened to it" in proc.stdout
    video = cv2.VideoCapture(str(rec / "run.mp4"))
    count = int(video.get(cv2.CAP_PROP_FRAME_COUNT))
    assert count == pytest.approx((TICKS / 30 + 10 + 1.5) * 30, abs=3)
    edit_tick(TICKS - 1, put("t", 1e300))(rec)  # not a time any run had
    assert_refused(jetbot_rt("report", str(rec), timeout=HANG_S), "t must be within")


def test_the_video_stops_at_its_cap(rec, monkeypatch, capsys):
    monkeypatch.setattr(report, "MAX_VIDEO_FRAMES", 7)
    args = argparse.Namespace(recording=str(rec), out=None, no_video=False)
    monkeypatch.setattr(report, "plot", lambda *a: False)
    assert report.run(args) == 0
    assert "(7 frames, 0.2 s; cut at 7 frames)" in capsys.readouterr().out
    video = cv2.VideoCapture(str(rec / "run.mp4"))
    assert int(video.get(cv2.CAP_PROP_FRAME_COUNT)) == 7


@pytest.mark.parametrize("name", ["meta.json", "ticks.jsonl"])
@pytest.mark.parametrize("kind", ["fifo", "dev-zero"])
def test_a_fifo_or_dev_zero_in_a_recording_is_refused_without_blocking(rec, name, kind):
    (fifo(name) if kind == "fifo" else link(name, "/dev/zero"))(rec)
    for command in ("replay", "report"):
        assert_refused(jetbot_rt(command, str(rec), timeout=HANG_S), name)


def test_a_telemetry_file_that_is_dev_zero_or_a_fifo_is_refused(tmp_path):
    (tmp_path / "zero.jsonl").symlink_to("/dev/zero")  # named by the user: followed
    os.mkfifo(tmp_path / "fifo.jsonl")
    for name in ("zero.jsonl", "fifo.jsonl"):
        assert_refused(jetbot_rt("report", str(tmp_path / name), timeout=HANG_S),
                       "not a regular file")


def test_outputs_planted_as_links_are_replaced_never_written_through(rec, tmp_path):
    victims = {}
    for name in ("run.png", "run.mp4"):
        victim = tmp_path / f"victim-{name}"
        victim.write_text("precious\n")
        (rec / name).symlink_to(victim)
        victims[name] = victim
    proc = jetbot_rt("report", str(rec), timeout=HANG_S)
    assert proc.returncode == 0, proc.stderr
    for name, victim in victims.items():
        assert victim.read_text() == "precious\n"
        assert not (rec / name).is_symlink() and (rec / name).stat().st_size > 1000
    assert sorted(p.name for p in rec.iterdir() if p.name.startswith(".")) == []


def test_a_directory_name_that_is_not_utf8_is_refused_not_a_crash(rec, tmp_path):
    name = os.path.join(os.fsencode(tmp_path), b"rec-\xff")
    os.rename(rec, name)
    for command in ("replay", "report"):
        proc = jetbot_rt(command, os.fsdecode(name), timeout=HANG_S)
        assert_refused(proc, "rec-\\xff: the path is not valid UTF-8 text")
    proc = jetbot_rt("report", str(tmp_path / "rec-ok"), "--out", os.fsdecode(name),
                     timeout=HANG_S)
    assert_refused(proc)


@pytest.mark.parametrize("case", ["meta-a-list", "rate-hz-0", "frame-past-its-tick",
                                  "config-policy-a-list", "summary-a-list"])
def test_malformed_recordings_end_to_end_exit_2_with_one_line(rec, case):
    MALFORMED[case][0](rec)
    for command in ("replay", "report"):
        assert_refused(jetbot_rt(command, str(rec), timeout=HANG_S), MALFORMED[case][1])


def test_a_recorded_policy_override_that_is_not_one_is_refused_by_replay(rec):
    edit_meta(lambda m: m["config"]["policy"].__setitem__("threads", 10**6))(rec)
    assert_refused(jetbot_rt("replay", str(rec), timeout=HANG_S),
                   "meta.json: config.policy: [policy] threads must be a number in [1, 64]")


def _file_size_limit(limit: int) -> Callable[[], None]:
    def apply() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    return apply


@pytest.mark.parametrize(("limit", "failing"), [(20_000, "run.png"), (400_000, "run.mp4")])
def test_a_full_disk_is_one_line_exit_1_and_leaves_nothing_half_written(rec, tmp_path, limit,
                                                                        failing):
    """RLIMIT_FSIZE makes every write past ``limit`` bytes fail (EFBIG), as a full disk does
    (ENOSPC), for PNG (matplotlib raises) and MP4 (OpenCV only warns: the file is checked)."""
    edit_tick(TICKS - 1, put("t", 8.0))(rec)  # some 8 s of video: larger than the limit
    out = tmp_path / "out"
    out.mkdir()
    (out / failing).write_text("the previous report\n")
    proc = jetbot_rt("report", str(rec), "--out", str(out), timeout=HANG_S,
                     preexec_fn=_file_size_limit(limit))
    assert proc.returncode == 1, proc.stderr
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert proc.stderr.startswith(f"jetbot-rt report: error: cannot write {out / failing}: ")
    assert (out / failing).read_text() == "the previous report\n"
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".")) == []


# ---- writing one: the directory may be someone else's ----------------------------------

@pytest.mark.parametrize("name", ["meta.json", "ticks.jsonl", "frames.mkv"])
def test_a_link_planted_in_the_record_directory_is_never_written_through(tmp_path, monkeypatch,
                                                                        name):
    """The record directory may have existed (empty) and be writable by someone else, who
    plants a link once it was found empty: every file of the recording is created new."""
    from jetbot_rt.recording import recorder as recorder_module
    from jetbot_rt.recording.recorder import Recorder

    victim = tmp_path / "victim"
    victim.write_text("precious\n")
    rec = tmp_path / "rec"
    rec.mkdir()
    monkeypatch.setattr(recorder_module, "open_directory",  # the race: checked, then planted
                        lambda path: os.open(path, os.O_RDONLY | os.O_DIRECTORY))
    (rec / name).symlink_to(victim)
    with pytest.raises(UsageError, match=f"cannot record to {rec}: .*File exists"):
        Recorder(rec, {"source": "test"}, (32, 32), 30.0, t0=0.0)
    assert victim.read_text() == "precious\n"


# ---- memory: a record holds only what is read, and the records held are bounded ----------

def retained_by(read: Callable[[], object]) -> tuple[object, int]:
    """What ``read`` returns and the bytes it keeps allocated (tracemalloc), once it is done."""
    gc.collect()
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        result = read()
        gc.collect()
        return result, tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()


def test_unknown_keys_and_long_texts_are_not_kept_so_a_records_memory_is_bounded(rec):
    """The review's case in small: lines full of ``{}`` (20 times their size as Python
    objects) under an unknown key, and texts of 200 KB. Before, each record kept it all."""
    pad = "[" + ",".join(["{}"] * 20_000) + "]"
    lines = (rec / "ticks.jsonl").read_text().splitlines()
    spoiled = [line[:-1] + f',"pad":{pad},"more":{{"a":{pad}}}}}' for line in lines]
    spoiled.append(json.dumps({"event": "note", "t": 1.0, "reason": "r" * 200_000}))
    (rec / "ticks.jsonl").write_text("\n".join(spoiled) + "\n")
    records, retained = retained_by(lambda: reader.read_records(rec / "ticks.jsonl", True))
    assert isinstance(records, list) and len(records) == len(spoiled)
    bound = len(records) * (reader.RECORD_BYTES + 3 * reader.TEXT_BYTES)
    assert retained <= bound, (retained, bound)  # before: ~60 MB for these 23 records
    assert all("pad" not in r and "more" not in r for r in records)
    assert len(records[-1]["reason"]) == reader.MAX_TEXT


def test_the_memory_the_records_hold_is_counted_not_underestimated(rec):
    """``RecordChecker.held`` is what the budget counts: it must not be less than the
    records really hold (tracemalloc), here for a recording as a run writes it."""
    _records, retained = retained_by(lambda: reader.read_records(rec / "ticks.jsonl", True))
    checker = reader.RecordChecker(True)
    for record in read_lines(rec):
        checker.check(record)
    assert retained <= checker.held * 1.1 + 4096, (retained, checker.held)


def test_more_records_than_the_memory_budget_is_one_line_exit_2(rec, monkeypatch):
    lines = (rec / "ticks.jsonl").read_text()
    events = "".join(json.dumps({"event": "e", "t": 0}) + "\n" for _ in range(3000))
    (rec / "ticks.jsonl").write_text(lines + events)
    monkeypatch.setattr(reader, "RECORDS_BYTES", 200_000)
    with pytest.raises(UsageError, match=r"ticks.jsonl line \d+: more records than 0 MiB"):
        Recording.open(rec)


@pytest.mark.parametrize("kind", ["link", "file", "not empty", "link parent"])
def test_a_record_directory_that_is_a_link_a_file_or_not_empty_is_refused(tmp_path, kind):
    """A link is refused even when it is ours (the second-uid cases, where it matters, are in
    test_hostile_user.py): nothing is written where it points."""
    from jetbot_rt.recording.recorder import Recorder

    target = tmp_path / "elsewhere"
    target.mkdir()
    rec = tmp_path / "rec"
    if kind == "link":
        rec.symlink_to(target)
    elif kind == "file":
        rec.write_text("")
    elif kind == "not empty":
        rec.mkdir()
        (rec / "old.txt").write_text("")
    else:
        (tmp_path / "parent").symlink_to(target)
        rec = tmp_path / "parent" / "rec"  # our own link among the parents: followed
        Recorder(rec, {"source": "test"}, (32, 32), 30.0, t0=0.0).close(timeout=None)
        assert sorted(p.name for p in (target / "rec").iterdir()) == [
            "frames.mkv", "meta.json", "summary.json", "ticks.jsonl"]
        return
    expected = {"link": "is a symbolic link", "file": "exists and is not a directory",
                "not empty": "exists and is not empty"}[kind]
    with pytest.raises(UsageError, match=f"record directory {rec} {expected}"):
        Recorder(rec, {"source": "test"}, (32, 32), 30.0, t0=0.0)
    assert list(target.iterdir()) == []

"""A training run's directory is untrusted on the way in and written without following links:
what is already in ``--out`` (a copied run, a shared directory, files another user planted)
never makes the trainer write through a link, block, or end in a traceback after training.

The review's examples as regression tests (a second uid where ownership matters), the sweep's
and ``eval --video``'s directories, and a seeded fuzz of ``metrics.csv`` read on resume.
"""

from __future__ import annotations

import os
import random
import shutil
import time
from pathlib import Path

import pytest
from hostile_user import as_user, needs_root, shared_dir, unused_uid
from train_runner import train_cli, train_here

from jetbot_rt.errors import UsageError

pytest.importorskip("pybullet")

TINY = ("train", "--task", "forward", "--num-envs", "1", "--workers", "0", "--seed", "3",
        "--no-progress", "--num-steps", "64", "--update-epochs", "1", "--num-minibatches", "2")
"""One update per 64 steps, one pass over it: the directory is the point, not the learning."""
HANG_S = 90.0
"""A run that takes longer is stuck: one interpreter start, torch's import, one tiny update."""
PLANTED = (".write_test", "learning_curve.png", "metrics.csv", "policy.onnx")


@pytest.fixture(scope="module")
def one_update(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A run directory after one 64-step update: checkpoint, policy, metrics, curve."""
    from jetbot_rt.train.cli import main

    out = tmp_path_factory.mktemp("one-update")
    assert main([*TINY, "--timesteps", "64", "--out", str(out)]) == 0  # in this process: fast
    return out


def copy_of(run: Path, where: Path) -> Path:
    shutil.copytree(run, where)
    return where


def victims(where: Path) -> dict[Path, bytes]:
    """Files a planted link points to, each with its content."""
    where.mkdir(exist_ok=True)
    found = {}
    for name in PLANTED:
        path = where / f"victim-{name.strip('.')}"
        path.write_bytes(f"precious {name}\n".encode())
        os.chmod(path, 0o600)
        found[path] = path.read_bytes()
    return found


def untouched(found: dict[Path, bytes]) -> None:
    for path, content in found.items():
        assert path.read_bytes() == content, path


def one_line_exit_2(result, needle: str) -> str:
    assert result.returncode == 2, result.stdout + result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], result.stderr
    assert "Traceback" not in result.stderr
    return lines[0]


def test_links_planted_in_a_run_directory_are_replaced_never_followed(tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    found = victims(tmp_path / "victims")
    for name, victim in zip(PLANTED, found, strict=True):
        (out / name).symlink_to(victim)
    result = train_here(capsys, *TINY, "--timesteps", "64", "--out", str(out))
    assert result.returncode == 0, result.stderr
    untouched(found)
    for name in ("learning_curve.png", "metrics.csv", "policy.onnx", "checkpoint.pt"):
        assert not (out / name).is_symlink() and (out / name).stat().st_size > 0, name
    assert not any(p.name.startswith(".write_test.") for p in out.iterdir())


def test_a_run_directory_that_is_a_link_is_refused_before_training(tmp_path, capsys):
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (tmp_path / "run").symlink_to(elsewhere)
    for command in ((*TINY, "--timesteps", "64"),
                    ("eval", "--episodes", "1", "--num-envs", "1", "--no-progress",
                     "--video")):
        result = train_here(capsys, *command, *(("--out",) if command[0] == "train" else ()),
                            str(tmp_path / "run"))
        one_line_exit_2(result, "a symbolic link")
    assert list(elsewhere.iterdir()) == []


@needs_root
def test_a_run_directory_of_another_user_is_refused_and_nothing_in_it_is_followed(
        tmp_path, capsys):
    """The review's example: H owns --out and has planted links; root trains there."""
    hostile = unused_uid()
    theirs = shared_dir(hostile)
    found = victims(tmp_path / "victims")
    try:
        planted = as_user(hostile, "import os, sys\nfor name, target in zip(sys.argv[2::2], "
                          "sys.argv[3::2]):\n    os.symlink(target, os.path.join(sys.argv[1], "
                          "name))\n", str(theirs),
                          *[w for pair in zip(PLANTED, map(str, found), strict=True)
                            for w in pair])
        assert planted.returncode == 0, planted.stderr
        started = time.monotonic()
        for resume in ((), ("--resume",)):
            result = train_here(capsys, *TINY, "--timesteps", "64", "--out", str(theirs),
                                *resume)
            one_line_exit_2(result, f"is owned by uid {hostile}")
        result = train_here(capsys, "eval", "--episodes", "1", "--num-envs", "1",
                            "--no-progress", "--video", str(theirs))
        one_line_exit_2(result, f"is owned by uid {hostile}")
        from jetbot_rt.train.sweep import sweep

        with pytest.raises(UsageError, match=f"is owned by uid {hostile}"):
            sweep("forward", theirs, seeds=[1], timesteps=64, num_envs=1)
        rootonly = tmp_path / "rootonly"
        rootonly.mkdir(mode=0o700)
        made = as_user(hostile, "import os, sys\nos.symlink(sys.argv[1], sys.argv[2])\n",
                       str(rootonly), str(theirs / "rootonly"))
        assert made.returncode == 0, made.stderr
        result = train_here(capsys, *TINY, "--timesteps", "64", "--out",
                            str(theirs / "rootonly" / "run"))
        one_line_exit_2(result, f"is a symbolic link of uid {hostile}")
        assert list(rootonly.iterdir()) == []
        assert time.monotonic() - started < HANG_S  # refused before any training
        untouched(found)
        assert sorted(p.name for p in theirs.iterdir()) == sorted([*PLANTED, "rootonly"])
    finally:
        shutil.rmtree(theirs)


@needs_root
def test_a_metrics_file_of_another_user_in_our_directory_is_not_resumed(one_update, capsys):
    """A directory others may write to (mode 0777, say): H's file at metrics.csv is theirs
    to change under us, so it is refused (one line, exit 2) before training."""
    hostile = unused_uid()
    ours = shared_dir(0)  # root's, where H can reach it
    try:
        os.chmod(ours, 0o755)
        out = copy_of(one_update, ours / "run")
        (out / "metrics.csv").unlink()
        os.chmod(out, 0o777)
        made = as_user(hostile, "import sys\nopen(sys.argv[1], 'w').write('x')\n",
                       str(out / "metrics.csv"))
        assert made.returncode == 0, made.stderr
        os.chmod(out, 0o700)
        before = (out / "checkpoint.pt").read_bytes()
        result = train_here(capsys, *TINY, "--timesteps", "128", "--out", str(out), "--resume")
        one_line_exit_2(result, f"owned by uid {hostile}")
        assert (out / "checkpoint.pt").read_bytes() == before
    finally:
        shutil.rmtree(ours)


@pytest.mark.parametrize("kind", ["symlink", "hard link", "directory", "dev-zero link"])
def test_a_metrics_file_that_is_not_ours_to_append_to_is_refused_on_resume(
        tmp_path, one_update, capsys, kind):
    out = copy_of(one_update, tmp_path / "run")
    metrics = out / "metrics.csv"
    victim = tmp_path / "victim.txt"
    victim.write_text("keep me\n")
    metrics.unlink()
    if kind == "symlink":
        metrics.symlink_to(victim)
    elif kind == "hard link":
        os.link(victim, metrics)
    elif kind == "directory":
        metrics.mkdir()
    else:
        metrics.symlink_to("/dev/zero")
    before = (out / "checkpoint.pt").read_bytes()
    result = train_here(capsys, *TINY, "--timesteps", "128", "--out", str(out), "--resume")
    one_line_exit_2(result, "metrics.csv")
    assert victim.read_text() == "keep me\n"
    assert (out / "checkpoint.pt").read_bytes() == before  # nothing trained


def test_a_fifo_at_metrics_csv_is_refused_on_resume_without_blocking(tmp_path, one_update):
    """The review's hang: appending to a FIFO nobody reads blocked for ever."""
    out = copy_of(one_update, tmp_path / "run")
    (out / "metrics.csv").unlink()
    os.mkfifo(out / "metrics.csv")
    result = train_cli(*TINY, "--timesteps", "128", "--out", str(out), "--resume",
                       timeout=HANG_S)
    one_line_exit_2(result, "not a regular file")


def row(header: str, **cells: str) -> str:
    return ",".join(cells.get(name, "1") for name in header.split(",")) + "\n"


BAD_METRICS = {
    "another file": (lambda header: "keep me\n", "the columns are 'keep me'"),
    "other columns": (lambda header: "wall_s,global_step\n1,64\n", "the columns are"),
    "a step that is not a number": (lambda header: header + "\n" + row(header, global_step="abc"),
                                    "global_step 'abc' is not a step count"),
    "NaN": (lambda header: header + "\n" + row(header, mean_return="nan"),
            "mean_return 'nan' is not a finite number"),
    "a short row": (lambda header: header + "\n1,2,3\n", "3 cells, expected"),
    "not UTF-8": (lambda header: "\udcff\n", "is not UTF-8"),
}


@pytest.mark.parametrize("case", sorted(BAD_METRICS))
def test_a_metrics_file_with_other_content_is_refused_before_training(
        tmp_path, one_update, capsys, case):
    """The review's traceback (``KeyError: 'mean_return'`` after all the training): now one
    line, exit 2, before any update (the checkpoint is unchanged)."""
    out = copy_of(one_update, tmp_path / "run")
    metrics = out / "metrics.csv"
    make, needle = BAD_METRICS[case]
    header = metrics.read_text().splitlines()[0]
    metrics.write_bytes(make(header).encode("utf-8", "surrogateescape"))
    before = (out / "checkpoint.pt").read_bytes()
    result = train_here(capsys, *TINY, "--timesteps", "128", "--out", str(out), "--resume")
    one_line_exit_2(result, needle)
    assert (out / "checkpoint.pt").read_bytes() == before


def test_a_resumed_run_keeps_the_metrics_it_read_and_appends_after_them(tmp_path, one_update,
                                                                       capsys):
    out = copy_of(one_update, tmp_path / "run")
    (out / "learning_curve.png").unlink()
    result = train_here(capsys, *TINY, "--timesteps", "128", "--out", str(out), "--resume")
    assert result.returncode == 0, result.stderr
    lines = (out / "metrics.csv").read_text().splitlines()
    assert [line.split(",")[1] for line in lines] == ["global_step", "64", "128"]
    assert (out / "learning_curve.png").stat().st_size > 0


def test_fuzzed_metrics_files_are_resumed_or_refused_in_one_line(tmp_path, one_update):
    """Seeded mutations of a real metrics.csv through the resume's reader, in this process,
    for a few seconds: each is either refused (one-line ``UsageError`` naming the file) or
    read into rows of finite numbers that the curve can be drawn from."""
    from jetbot_rt.train.ppo import CURVE, METRIC_FIELDS
    from jetbot_rt.train.run_dir import RunDirectory

    out = copy_of(one_update, tmp_path / "run")
    metrics = out / "metrics.csv"
    original = metrics.read_bytes()
    body = original.index(b"\n") + 1
    pieces = [b",", b"\n", b"\r\n", b'"', b"\x00", b"nan", b"inf", b"-1e400", b"9" * 40,
              b"\xff", b"\xc3\xa9", b"abc", b"", b" ", b"1e3", b",,,,", b"update", b"0", b"12.5",
              b"-3", b"7", b"\n\n"]
    rng = random.Random(25)
    accepted = refused = plotted = 0
    deadline = time.monotonic() + 4.0
    cases = 0
    while cases < 400 and time.monotonic() < deadline:
        data = bytearray(original)
        for _ in range(rng.randint(1, 3)):  # mostly in the rows: the header is one line
            at = rng.randrange(min(body, len(data)) if rng.random() < 0.8 else 0, len(data) + 1)
            how = rng.random()
            lines = bytes(data).split(b"\n")
            if how < 0.3 and len(lines) > 2:  # one cell of a row, the row kept whole
                number = rng.randrange(1, len(lines) - 1)
                cells = lines[number].split(b",")
                cells[rng.randrange(len(cells))] = rng.choice(pieces[4:])
                lines[number] = b",".join(cells)
                data = bytearray(b"\n".join(lines))
            elif how < 0.4:
                data[at:at + rng.randint(0, 3)] = rng.choice(pieces)
            elif how < 0.5 and data:
                data[at % len(data)] = rng.randrange(256)
            elif how < 0.8:
                data[at:] = data[at:] + data[: rng.randint(0, len(data))]
            else:
                del data[at:]
        metrics.write_bytes(bytes(data))
        run = RunDirectory(out, METRIC_FIELDS)
        try:
            run.prepare(resume=True)
        except UsageError as exc:
            refused += 1
            assert "\n" not in str(exc) and "metrics" in str(exc), str(exc)
        else:
            accepted += 1
            assert all(len(row) == len(METRIC_FIELDS) for row in run.rows)
            assert all(v is None or abs(v) < float("inf") for row in run.rows for v in row)
            if plotted < 2:
                run.plot_curve("fuzz", CURVE)
                plotted += 1
        finally:
            run.close()
        cases += 1
    assert refused > 0 and accepted > 0, (refused, accepted)
    assert cases >= 50


def test_the_sweep_writes_its_table_and_trials_without_following_links(tmp_path):
    from jetbot_rt.train.out_dir import own_directory, writable_directory
    from jetbot_rt.train.sweep import COLUMNS, write_table

    out = tmp_path / "sweep"
    out.mkdir()
    found = victims(tmp_path / "victims")
    for name, victim in zip(("sweep.csv", "sweep.md"), found, strict=False):
        (out / name).symlink_to(victim)
    (out / "default-seed1").symlink_to(tmp_path / "victims")
    fd = writable_directory(out)
    try:
        write_table([dict.fromkeys(COLUMNS, 1)], fd, out)
        with pytest.raises(UsageError, match="a symbolic link"):
            own_directory("default-seed1", "trial directory", parent=fd,
                          display=out / "default-seed1")
    finally:
        os.close(fd)
    untouched(found)
    assert (out / "sweep.csv").read_text().startswith("trial,config")
    assert not (out / "sweep.md").is_symlink()

"""Checkpoints are untrusted input: whatever file ``export``, ``train --init`` or ``train
--resume`` is handed, it is refused in one line with exit 2 or used, never a traceback, a
hang, or code run from the file."""

from __future__ import annotations

import contextlib
import io
import json
import os
import signal
import subprocess
import sys
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnx")

from checkpoint_fuzz import valid_state  # noqa: E402
from train_runner import train_main  # noqa: E402

from jetbot_rt.train.checkpoint import MAX_CHECKPOINT_BYTES  # noqa: E402

FUZZER = Path(__file__).with_name("checkpoint_fuzz.py")


@contextlib.contextmanager
def no_hang(seconds: float = 30.0) -> Iterator[None]:
    """A blocking ``open`` or read (a FIFO, /dev/zero) fails the test instead of stalling it:
    SIGALRM interrupts the system call and its handler raises."""
    def hung(signum: int, frame: Any) -> None:
        raise TimeoutError(f"still reading after {seconds} s")

    previous = signal.signal(signal.SIGALRM, hung)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def jetbot_train(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str]:
    """``jetbot-train ARGS`` in this process: the exit code and stderr."""
    with no_hang():
        code, _, err = train_main(capsys, *args)
    return code, err


def one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]


def with_weights(change: Callable[[dict[str, Any]], None]) -> Callable[[], dict[str, Any]]:
    def build() -> dict[str, Any]:
        state = valid_state()
        change(state["model"])
        return state
    return build


def with_fields(**fields: Any) -> Callable[[], dict[str, Any]]:
    def build() -> dict[str, Any]:
        state = valid_state()
        for key, value in fields.items():
            if value is KeyError:
                del state[key]
            else:
                state[key] = value
        return state
    return build


def with_model_config(**fields: Any) -> Callable[[], dict[str, Any]]:
    def build() -> dict[str, Any]:
        state = valid_state()
        state["model_config"] = {**state["model_config"], **fields}
        return state
    return build


def _set(name: str, value: Any) -> Callable[[dict[str, Any]], None]:
    return lambda weights: weights.__setitem__(name, value)


def _poison(value: float) -> Callable[[dict[str, Any]], None]:
    def change(weights: dict[str, Any]) -> None:
        weights["value_head.bias"][0] = value
    return change


class Reduce:
    """Unpickling it would run ``os.system``: a weights-only load must refuse it."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple[Any, tuple[str]]:
        return os.system, (f"touch {self.marker}",)


FIELD_DEFECTS: list[tuple[str, Callable[[], Any], str]] = [
    ("a list, not a dict", lambda: [1, 2], "not a jetbot-train checkpoint (format"),
    ("another format tag", with_fields(format="other/1"), "(format jetbot_rt.ppo/1)"),
    ("a tensor as format tag", with_fields(format=torch.zeros(2)), "(format"),
    ("an unknown task", with_fields(task="fly"), "task must be one of"),
    ("no model config", with_fields(model_config=KeyError), "model_config must be a dict"),
    ("an unknown algo", with_fields(algo="sac"), "algo must be one of"),
    ("a string for an integer", with_model_config(hidden="8"), "model_config.hidden must be"),
    ("a network over the parameter cap", with_model_config(hidden=60_000, image_size=512),
     "parameters, more than"),
    ("an unknown network option", with_model_config(depth=3), "unknown model option(s) depth"),
    ("an initial log std too large to build", with_model_config(init_log_std=10**30),
     "model_config.init_log_std must be a number in"),
    ("two channel counts", with_model_config(channels=[2, 2]), "model_config.channels"),
    ("a kernel larger than the image", with_model_config(first_kernel=9, first_stride=1),
     "model_config.first_kernel"),
    ("weights not a dict", with_fields(model=[1, 2]), "model must be a dict of weights"),
    ("a missing weight", with_weights(lambda w: w.pop("mu_head.bias")),
     "lacks weight(s) mu_head.bias"),
    ("an extra weight", with_weights(_set("extra.weight", torch.zeros(1))),
     "has weight(s) the network has not: extra.weight"),
    ("a weight of the wrong shape", with_weights(_set("mu_head.bias", torch.zeros(3))),
     "mu_head.bias has shape [3], expected [2]"),
    ("a float64 weight", with_weights(_set("mu_head.bias", torch.zeros(2, dtype=torch.float64))),
     "must be a dense torch.float32 tensor"),
    ("a number for a weight", with_weights(_set("mu_head.bias", 1.0)), "must be a tensor"),
    ("a NaN weight", with_weights(_poison(float("nan"))), "value_head.bias holds non-finite"),
    ("an infinite weight", with_weights(_poison(float("inf"))), "holds non-finite"),
    ("a view claiming 10^12 elements",
     with_weights(_set("mu_head.bias", torch.zeros(1).expand(10**12))), "has shape [1000000"),
    ("a NaN max_speed", with_fields(max_speed=float("nan")), "max_speed must be a number"),
    ("a max_speed above 1", with_fields(max_speed=5), "max_speed must be a number in [0, 1]"),
    ("a negative step count", with_fields(global_step=-1), "global_step must be an integer"),
    ("a NaN reward scale", with_fields(reward_rms={"mean": 0.0, "var": float("nan"),
                                                   "count": 1.0}), "var must be a number"),
]


def test_the_valid_tiny_checkpoint_exports_with_exit_0(tmp_path, capsys):
    path = tmp_path / "checkpoint.pt"
    torch.save(valid_state(), path)
    code, err = jetbot_train(capsys, "export", "--checkpoint", str(path), "--out",
                             str(tmp_path / "p.onnx"))
    assert code == 0, err
    assert (tmp_path / "p.onnx").stat().st_size > 0


@pytest.mark.parametrize(("what", "build", "needle"), FIELD_DEFECTS,
                         ids=[case[0] for case in FIELD_DEFECTS])
def test_a_well_formed_but_wrong_checkpoint_is_one_line_and_exit_2(tmp_path, capsys, what,
                                                                    build, needle):
    path = tmp_path / "checkpoint.pt"
    torch.save(build(), path)
    out = tmp_path / "p.onnx"
    code, err = jetbot_train(capsys, "export", "--checkpoint", str(path), "--out", str(out))
    assert code == 2, err
    assert needle in one_line(err)
    assert not out.exists()


def _fifo(path: Path) -> None:
    os.mkfifo(path)


def _dev_zero(path: Path) -> None:
    path.symlink_to("/dev/zero")


def _huge(path: Path) -> None:
    with path.open("wb") as handle:  # sparse: no disk used
        handle.truncate(MAX_CHECKPOINT_BYTES + 1)


def _truncated(path: Path) -> None:
    torch.save(valid_state(), path)
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def _legacy_format(path: Path) -> None:
    torch.save(valid_state(), path, _use_new_zipfile_serialization=False)


def _deflated(path: Path) -> None:
    """The valid checkpoint's entries compressed: a small file could expand to any size."""
    plain = io.BytesIO()
    torch.save(valid_state(), plain)
    with zipfile.ZipFile(plain) as source, zipfile.ZipFile(path, "w") as target:
        for entry in source.infolist():
            target.writestr(entry.filename, source.read(entry), zipfile.ZIP_DEFLATED)


FILE_DEFECTS: list[tuple[str, Callable[[Path], None], str]] = [
    ("missing", lambda path: None, "No such file or directory"),
    ("a directory", lambda path: path.mkdir(), "a directory"),
    ("a FIFO", _fifo, "not a regular file"),
    ("a symlink to /dev/zero", _dev_zero, "not a regular file"),
    ("larger than the cap", _huge, "is larger than 128 MiB"),
    ("empty", lambda path: path.write_bytes(b""), "not a zip archive"),
    ("text", lambda path: path.write_text("not a checkpoint"), "not a zip archive"),
    ("truncated", _truncated, "not a jetbot-train checkpoint"),
    ("torch's legacy format", _legacy_format, "not a zip archive"),
    ("compressed entries", _deflated, "is compressed"),
]


@pytest.mark.parametrize(("what", "make", "needle"), FILE_DEFECTS,
                         ids=[case[0] for case in FILE_DEFECTS])
def test_a_file_that_is_not_a_checkpoint_is_refused_without_blocking(tmp_path, capsys, what,
                                                                      make, needle):
    path = tmp_path / "checkpoint.pt"
    make(path)
    out = tmp_path / "p.onnx"
    code, err = jetbot_train(capsys, "export", "--checkpoint", str(path), "--out", str(out))
    assert code == 2, err
    assert needle in one_line(err)
    assert not out.exists()


def test_a_checkpoint_whose_pickle_would_run_code_is_refused_and_runs_nothing(tmp_path,
                                                                            capsys):
    marker = tmp_path / "ran"
    path = tmp_path / "checkpoint.pt"
    torch.save({**valid_state(), "args": Reduce(marker)}, path)
    code, err = jetbot_train(capsys, "export", "--checkpoint", str(path), "--out",
                             str(tmp_path / "p.onnx"))
    assert code == 2, err
    assert "its pickle holds more than tensors and plain data" in one_line(err)
    assert not marker.exists()


@pytest.mark.parametrize("algo", ["ppo", "dagger"])
def test_train_init_refuses_a_bad_checkpoint_in_one_line_before_any_env_starts(tmp_path,
                                                                               capsys, algo):
    task = "forward" if algo == "ppo" else "seek"
    for name, build in (("nan", with_weights(_poison(float("nan")))),
                        ("shape", with_weights(_set("mu_head.bias", torch.zeros(3))))):
        path = tmp_path / f"{name}.pt"
        torch.save(build(), path)
        code, err = jetbot_train(capsys, "train", "--task", task, "--algo", algo, "--init",
                                 str(path), "--out", str(tmp_path / "run"), "--no-progress")
        assert code == 2, err
        assert str(path) in one_line(err)
    fifo = tmp_path / "fifo.pt"
    os.mkfifo(fifo)
    code, err = jetbot_train(capsys, "train", "--task", task, "--algo", algo, "--init",
                             str(fifo), "--out", str(tmp_path / "run"), "--no-progress")
    assert code == 2 and "not a regular file" in one_line(err)


def _optimizer_entry(state: dict[str, Any], key: str, value: Any) -> dict[str, Any]:
    state["optimizer"]["state"][0][key] = value
    return state


RESUME_DEFECTS: list[tuple[str, Callable[[], dict[str, Any]], str]] = [
    ("a moment of the wrong shape",
     lambda: _optimizer_entry(valid_state(), "exp_avg", torch.zeros(1)), "exp_avg of parameter 0"),
    ("a negative second moment",
     lambda: _optimizer_entry(valid_state(), "exp_avg_sq",
                              -torch.ones_like(valid_state()["optimizer"]["state"][0]["exp_avg"])),
     "has negative values"),
    ("a NaN step", lambda: _optimizer_entry(valid_state(), "step", torch.tensor(float("nan"))),
     "step of parameter 0 must be a finite scalar"),
    ("betas as a tensor",
     lambda: {**valid_state(), "optimizer": {**valid_state()["optimizer"], "param_groups": [
         {**valid_state()["optimizer"]["param_groups"][0], "betas": torch.zeros(2)}]}},
     "optimizer betas is Tensor"),
    ("no optimizer", with_fields(optimizer=KeyError), "holds no optimizer state"),
    ("a DAgger checkpoint", with_fields(algo="dagger"), "was written by dagger, not ppo"),
    ("another task's", with_fields(task="seek"), "is for task 'seek', not 'forward'"),
]


@pytest.mark.parametrize(("what", "build", "needle"), RESUME_DEFECTS,
                         ids=[case[0] for case in RESUME_DEFECTS])
def test_resume_refuses_a_checkpoint_it_cannot_continue_in_one_line(tmp_path, capsys, what,
                                                                    build, needle):
    run = tmp_path / "run"
    run.mkdir()
    torch.save(build(), run / "checkpoint.pt")
    before = (run / "checkpoint.pt").read_bytes()
    code, err = jetbot_train(capsys, "train", "--task", "forward", "--algo", "ppo", "--resume",
                             "--out", str(run), "--no-progress", "--num-envs", "1")
    assert code == 2, err
    assert needle in one_line(err)
    assert (run / "checkpoint.pt").read_bytes() == before


def test_dagger_resume_refuses_a_ppo_checkpoint(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    torch.save({**valid_state(), "task": "seek"}, run / "checkpoint.pt")
    code, err = jetbot_train(capsys, "train", "--task", "seek", "--algo", "dagger", "--resume",
                             "--out", str(run), "--no-progress")
    assert code == 2, err
    assert "was written by ppo, not dagger" in one_line(err)


def test_mutated_checkpoints_are_refused_in_one_line_or_exported(tmp_path):
    """Seeded fuzzing for a few seconds: fields spoiled at any depth, bytes flipped, cut or
    inserted. Every case ends in exit 0 (the file written) or exit 2 with one line (nothing
    written), and the resume path accepts or refuses it; nothing escapes, nothing hangs."""
    result = subprocess.run([sys.executable, str(FUZZER), "7", "6", str(tmp_path)],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-3000:]
    cases = [json.loads(line) for line in result.stdout.splitlines()]
    assert len(cases) >= 10, result.stderr[-3000:]
    for case in cases:
        assert "escaped" not in case and "resume_escaped" not in case, case
        if case["code"] == 0:
            assert case["wrote"], case
        else:
            assert case["code"] == 2 and not case["wrote"], case
            one_line(case["stderr"])
    assert {case["code"] for case in cases} == {0, 2}


def test_the_largest_network_the_options_allow_has_a_readable_checkpoint():
    """Its weights and Adam's two moments (float32) and a margin fit the reader's cap."""
    from jetbot_rt.train.hyperparams import MAX_PARAMETERS

    assert 3 * 4 * MAX_PARAMETERS + 16 * 1024 * 1024 < MAX_CHECKPOINT_BYTES

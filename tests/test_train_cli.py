"""``jetbot-train`` end to end, as a user runs it: a smoke training run whose checkpoint and
ONNX the runtime loads and drives, resume, export with parity, eval JSON, and bad input."""

from __future__ import annotations

import contextlib
import json
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch
from runner import run_cli
from train_runner import JETBOT_TRAIN, train_cli, train_here, train_main

from jetbot_rt.train.env import POLICY_IMAGE_SIZE

pytest.importorskip("pybullet")

METADATA = {
    "jetbot_rt.layout": "NHWC",
    "jetbot_rt.color_order": "RGB",
    "jetbot_rt.pixel_range": "0-255",
    "jetbot_rt.max_speed": "0.1",
    "jetbot_rt.task": "forward",
    "jetbot_rt.input_size": f"{POLICY_IMAGE_SIZE}x{POLICY_IMAGE_SIZE}",
}


QUICK_UPDATE = ("--num-steps", "64", "--update-epochs", "1", "--num-minibatches", "2")
"""Smoke runs: two rollouts of 64 steps, one pass of two minibatches per update (the
defaults' update epochs took most of each run's time and prove nothing more)."""
SMOKE = ("train", "--task", "forward", "--timesteps", "128", "--num-envs", "1", "--workers", "0",
         "--seed", "3", "--no-progress", *QUICK_UPDATE)


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("smoke")
    result = train_cli(*SMOKE, "--out", str(out))
    assert result.returncode == 0, result.stderr
    return out


def test_smoke_training_writes_checkpoint_onnx_metrics_and_curve(smoke_run):
    for name in ("checkpoint.pt", "policy.onnx", "metrics.csv", "learning_curve.png"):
        assert (smoke_run / name).stat().st_size > 0, name
    rows = (smoke_run / "metrics.csv").read_text().splitlines()
    assert rows[0].startswith("update,global_step,wall_s,steps_per_s")
    assert [r.split(",")[1] for r in rows[1:]] == ["64", "128"]
    assert (smoke_run / "policy.onnx").stat().st_size < 2_000_000


@pytest.mark.skipif(torch.cuda.is_available(), reason="the default device is CUDA here")
def test_device_cpu_trains_the_same_weights_as_the_default(smoke_run, tmp_path, capsys):
    result = train_here(capsys, *SMOKE, "--out", str(tmp_path), "--device", "cpu")
    assert result.returncode == 0, result.stderr
    default = torch.load(smoke_run / "checkpoint.pt", weights_only=True)
    on_cpu = torch.load(tmp_path / "checkpoint.pt", weights_only=True)
    assert on_cpu["args"]["device"] == "cpu" and default["args"]["device"] == "auto"
    for name, tensor in default["model"].items():
        assert torch.equal(tensor, on_cpu["model"][name]), name


def test_runtime_loads_and_drives_the_trained_onnx(smoke_run, tmp_path, monkeypatch):
    monkeypatch.setenv("JETBOT_RT_RUNTIME_DIR", str(tmp_path))  # beside any other jetbot-rt
    patient = tmp_path / "patient.toml"  # the watchdog is not the point (starved: it trips)
    patient.write_text("[loop]\nwatchdog_timeout = 1.0\n")
    result = run_cli(["run", "--backend", "sim", "--policy", str(smoke_run / "policy.onnx"),
                      "--duration", "0.5", "--config", str(patient)],
                     telemetry=tmp_path / "t.jsonl")
    assert result.returncode == 0, result.stderr
    ticks = result.ticks
    assert len(ticks) >= 5  # of 15 at 30 Hz: how many a loaded machine keeps is not the point
    assert all(np.isfinite(t["mu"]).all() and len(t["cmd"]) == 2 for t in ticks)
    assert any(abs(c) > 0 for t in ticks for c in t["cmd"])  # it did drive


def test_resume_continues_the_step_count(smoke_run, tmp_path, capsys):
    run = tmp_path / "resumed"
    shutil.copytree(smoke_run, run)
    result = train_here(capsys, "train", "--task", "forward", "--timesteps", "192",
                        "--num-envs", "1", "--workers", "0", "--out", str(run), "--resume",
                        "--no-progress", *QUICK_UPDATE)
    assert result.returncode == 0, result.stderr
    steps = [r.split(",")[1] for r in (run / "metrics.csv").read_text().splitlines()[1:]]
    assert steps == ["64", "128", "192"]
    state = torch.load(run / "checkpoint.pt", weights_only=True)
    assert state["global_step"] == 192 and state["update"] == 3


def test_export_layout_metadata_and_parity(smoke_run, tmp_path):
    out = tmp_path / "exported.onnx"
    result = train_cli("export", "--checkpoint", str(smoke_run / "checkpoint.pt"),
                       "--out", str(out))
    assert result.returncode == 0, result.stderr
    assert "max abs diff" in result.stdout
    model = onnx.load(str(out))
    assert model.opset_import[0].version == 16
    props = {p.key: p.value for p in model.metadata_props}
    assert METADATA.items() <= props.items()
    assert "max_speed" in props["jetbot_rt.action"]
    session = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    (obs,) = session.get_inputs()
    assert obs.name == "obs" and obs.type == "tensor(float)"
    assert obs.shape[1:] == [POLICY_IMAGE_SIZE, POLICY_IMAGE_SIZE, 3]
    assert [o.name for o in session.get_outputs()] == ["mu", "log_std", "value"]

    from jetbot_rt.train.checkpoint import load_checkpoint

    torch_model = load_checkpoint(smoke_run / "checkpoint.pt").model()
    images = np.random.default_rng(7).integers(
        0, 256, (4, POLICY_IMAGE_SIZE, POLICY_IMAGE_SIZE, 3)).astype(np.float32)
    got = session.run(None, {"obs": images})
    with torch.no_grad():
        want = [t.numpy() for t in torch_model(torch.from_numpy(images))]
    assert [g.shape for g in got] == [(4, 2), (4, 2), (4, 1)]
    for g, w in zip(got, want, strict=True):
        assert np.max(np.abs(g - w)) < 1e-4


def imported_torch(importtime_log: str) -> list[str]:
    """The torch modules in ``python -X importtime``'s log (stderr)."""
    names = [line.rsplit("|", 1)[-1].strip() for line in importtime_log.splitlines()
             if line.startswith("import time:")]
    assert "jetbot_rt" in names, importtime_log[-2000:]  # the log is there
    return [n for n in names if n == "torch" or n.startswith("torch.")]


def test_eval_json_has_the_fields_and_never_imports_torch(smoke_run):
    """An ONNX policy is evaluated through onnxruntime: no torch import (~2-5 s) in eval."""
    result = subprocess.run(
        [sys.executable, "-X", "importtime", JETBOT_TRAIN, "eval", "--policy",
         str(smoke_run / "policy.onnx"), "--task", "forward", "--episodes", "1",
         "--num-envs", "1", "--json"], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]
    assert imported_torch(result.stderr) == []
    report = json.loads(result.stdout)  # stdout is exactly one JSON object
    assert report["episodes"] == 1
    assert 0.0 <= report["success_rate"] <= 1.0
    assert np.isfinite(report["mean_return"]) and report["mean_final_distance"] > 0
    assert report["deadband_lift"] is None and report["calibrated_policy"] is False


@pytest.mark.skipif(
    not (Path(__file__).parents[1] / "jetbot_rt" / "policies" / "forward.onnx").exists(),
    reason="no bundled policy",
)
def test_eval_without_policy_uses_the_bundled_one_and_it_reaches_the_block():
    result = train_cli("eval", "--episodes", "2", "--num-envs", "2", "--json")
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report["policy"].endswith("jetbot_rt/policies/forward.onnx")
    assert report["episodes"] == 2
    assert report["mean_final_distance"] < 0.3


def _one_line_exit_2(result: subprocess.CompletedProcess, needle: str) -> None:
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], result.stderr


def test_bad_input_is_one_line_and_exit_2(tmp_path, smoke_run, capsys):
    a_file = tmp_path / "plain.txt"
    a_file.write_text("not a checkpoint")
    bad_train = tmp_path / "bad.toml"
    bad_train.write_text("[train]\ngama = 0.9\n")
    bad_value = tmp_path / "value.toml"
    bad_value.write_text("[train]\nnum_steps = \"64\"\n[train.model]\nhidden = 8\n")
    out = tmp_path / "m.onnx"
    cases = [
        (["train", "--task", "sideways", "--timesteps", "10", "--out", str(tmp_path / "x")],
         "unknown task 'sideways'"),
        (["train", "--config", str(bad_train), "--out", str(tmp_path / "x")],
         "unknown training option(s) gama"),
        (["train", "--timesteps", "0", "--out", str(tmp_path / "x")], "--timesteps"),
        (["train", "--config", str(bad_value), "--out", str(tmp_path / "x")],
         "[train] num_steps must be an integer, got '64'"),
        (["train", "--model-image-size", "7", "--out", str(tmp_path / "x")],
         "--model-image-size must be 8 .. 1024, got 7"),
        (["train", "--algo", "dagger", "--task", "seek", "--snapshots", "-1", "--out",
          str(tmp_path / "x")], "--snapshots must be >= 0, got -1"),
        (["train", "--timesteps", "10", "--num-envs", "-1", "--out", str(tmp_path / "x")],
         "--num-envs"),
        (["train", "--timesteps", "10", "--num-envs", "2", "--workers", "1", "--out",
          str(tmp_path / "x")], "--workers must be 0"),
        (["train", "--timesteps", "10", "--out", str(a_file / "sub")], "cannot write"),
        (["export", "--checkpoint", str(tmp_path / "missing.pt"), "--out", str(out)],
         "No such file or directory"),
        (["export", "--checkpoint", str(a_file), "--out", str(out)],
         "not a jetbot-train checkpoint"),
        (["export", "--checkpoint", str(smoke_run / "policy.onnx"), "--out", str(out)],
         "not a jetbot-train checkpoint"),
        (["export", "--checkpoint", str(smoke_run / "checkpoint.pt"), "--out",
          str(a_file / "m.onnx")],
         "cannot write"),
        (["eval", "--task", "sideways", "--episodes", "1"], "unknown task 'sideways'"),
        (["eval", "--ablate", "sepia", "--episodes", "1"], "invalid choice"),
        (["eval", "--policy", str(a_file), "--episodes", "1"], "not a loadable ONNX model"),
        (["eval", "--episodes", "0"], "--episodes"),
        (["train", "--algo", "dagger", "--task", "avoid", "--turn-weight", "-1", "--out",
          str(tmp_path / "x")], "--turn-weight must be >= 0, got -1"),
        (["train", "--algo", "dagger", "--task", "seek", "--mirror", "0.5", "--out",
          str(tmp_path / "x")], "--mirror needs an expert with symmetric(info)"),
    ]
    # Each case in this process (an interpreter and torch start per case cost ~3-6 s each);
    # two of them, one refused by the parser and one by the command, through the console
    # script as a user runs it.
    for args, needle in cases:
        code, _, err = train_main(capsys, *args)
        _one_line_exit_2(subprocess.CompletedProcess(args, code, "", err), needle)
    for args, needle in (cases[0], cases[10]):
        _one_line_exit_2(train_cli(*args), needle)


def test_bad_device_or_restarts_is_one_line_and_exit_2_before_training(tmp_path, capsys):
    from jetbot_rt.train.cli import main

    cases = [(["--device", "gpu"], "--device must be auto, cpu, cuda or cuda:N"),
             (["--ray-max-restarts", "-1"], "--ray-max-restarts must be >= 0"),
             (["--step-penalty", "-0.1"], "--step-penalty must be >= 0"),
             (["--target-kl", "0"], "--target-kl must be > 0")]
    if not torch.cuda.is_available():  # CUDA asked for on a machine without it
        cases.append((["--device", "cuda"], "--device cuda: CUDA is not available"))
    for flags, needle in cases:
        out = tmp_path / flags[1]
        assert main(["train", *flags, "--out", str(out)]) == 2
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and needle in lines[0], lines
        assert not out.exists()  # refused before anything was written or started


def test_help_lists_the_tasks_and_shows_defaults(capsys):
    code, out, _ = train_main(capsys, "--help")
    assert code == 0
    for name in ("forward", "seek"):
        assert f"{name} --" in " ".join(out.split())
    text = " ".join(train_main(capsys, "train", "--help")[1].split())
    assert "(default 0.99)" in text and "seek: 300000" in text  # gamma, seek's timesteps
    assert "--timesteps TOTAL_TIMESTEPS" in text and "--total-timesteps" not in text, \
        "one name in --help and the docs"
    import argparse

    from jetbot_rt.train.flags import add_ppo_arguments

    parser = argparse.ArgumentParser()
    add_ppo_arguments(parser)
    for flag in ("--timesteps", "--total-timesteps"):  # the field's own name still works
        assert parser.parse_args([flag, "500"]).total_timesteps == 500
    text = " ".join(train_main(capsys, "eval", "--help")[1].split())
    assert "--ablate" in text and "(default: 10000)" in text


def test_help_and_a_refused_flag_never_import_torch():
    """The parser is built from torch-free dataclasses (``train/hyperparams.py``)."""
    code = ("import sys\n"
            "from jetbot_rt.train.cli import main\n"
            "def code(*argv):\n"
            "    try:\n        return main(list(argv))\n"
            "    except SystemExit as exc:\n        return exc.code\n"
            "assert code('--help') == 0 and code('eval', '--help') == 0\n"
            "assert code('train', '--task', 'sideways') == 2\n"
            "assert code('train', '--gama', '0.9') == 2\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] == 'torch'))\n")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip().splitlines()[-1] == "[]"


def test_without_the_train_extra_one_line_names_it():
    code = ("import sys; sys.modules['torch'] = None\n"
            "from jetbot_rt.train.cli import main\n"
            "sys.exit(main(['train', '--task', 'seek']))\n")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            timeout=60)
    _one_line_exit_2(result, "pip install 'jetbot_rt[sim,train]'")
    assert "torch" in result.stderr


@pytest.mark.parametrize("overlap", [(), ("--overlap",)], ids=["sync", "overlap"])
def test_ctrl_c_saves_a_checkpoint_and_prints_the_resume_command(tmp_path, overlap):
    """With ``--overlap``: from the first update on the next rollout is in flight whenever
    Ctrl-C comes (in the update or waiting for it), and the workers are ended all the same."""
    out = tmp_path / "run"
    args = ["train", "--task", "seek", "--algo", "ppo", "--timesteps", "100000",
            "--num-envs", "1", "--num-steps", "16", "--update-epochs", "1", "--out", str(out),
            "--no-progress", *overlap]
    # a shell's background job inherits SIGINT ignored; a user's terminal delivers it
    proc = subprocess.Popen([JETBOT_TRAIN, *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 120
        while not (out / "metrics.csv").exists() and time.monotonic() < deadline:
            time.sleep(0.2)
        assert (out / "metrics.csv").exists(), "no update finished"
        proc.send_signal(signal.SIGINT)
        _, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, stderr
    assert "Traceback" not in stderr and "pending call" not in stderr, stderr
    resume = stderr.strip().splitlines()[-1].strip()
    assert resume.startswith("jetbot-train train") and resume.endswith("--resume")
    state = torch.load(out / "checkpoint.pt", weights_only=True)
    assert state["global_step"] >= 16 and state["task"] == "seek"
    assert (out / "learning_curve.png").stat().st_size > 0
    assert (out / "policy.onnx").stat().st_size > 0


def test_init_starts_from_another_tasks_checkpoint(smoke_run, tmp_path, capsys):
    out = tmp_path / "seek"
    result = train_here(capsys, "train", "--task", "seek", "--algo", "ppo",
                        "--timesteps", "32",
                        "--num-envs", "1", "--workers", "0", "--num-steps", "32", "--out",
                        str(out), "--no-progress", "--init", str(smoke_run / "checkpoint.pt"),
                        "--update-epochs", "1", "--learning-rate", "0")
    assert result.returncode == 0, result.stderr
    start = torch.load(smoke_run / "checkpoint.pt", weights_only=True)["model"]
    after = torch.load(out / "checkpoint.pt", weights_only=True)
    assert after["task"] == "seek" and after["global_step"] == 32
    assert all(torch.equal(start[k], after["model"][k]) for k in start)  # lr 0: unchanged


def _spawned_workers(pid: int) -> list[int]:
    """The multiprocessing workers among the children of ``pid``."""
    children = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        with contextlib.suppress(OSError):
            children += (task / "children").read_text().split()
    workers = []
    for child in children:
        with contextlib.suppress(OSError):
            if b"spawn_main" in Path(f"/proc/{child}/cmdline").read_bytes():
                workers.append(int(child))
    return workers


def test_ctrl_c_during_a_dagger_collection_ends_the_workers_at_once(tmp_path):
    """An iteration's collection is one call to the workers (hours here): Ctrl-C in it ends
    them instead of waiting for it, and saves and exits 130 as ever."""
    out = tmp_path / "run"
    args = ["train", "--task", "seek", "--out", str(out), "--no-progress",
            "--steps-per-iteration", "10000000"]
    proc = subprocess.Popen([JETBOT_TRAIN, *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 120
        while len(_spawned_workers(proc.pid)) < 2 and time.monotonic() < deadline:
            time.sleep(0.2)
        assert len(_spawned_workers(proc.pid)) == 2, "no env workers"
        # mostly mid-collection; under load still in the workers' start, which saves too
        time.sleep(4)
        assert proc.poll() is None
        proc.send_signal(signal.SIGINT)
        # a close() that waited for the collection would outlast this by hours
        _, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, stderr
    assert "Traceback" not in stderr and "pending call" not in stderr, stderr
    assert stderr.strip().splitlines()[-1].strip().endswith("--resume")
    assert (out / "policy.onnx").stat().st_size > 0

"""``jetbot-train train --ray``: PPO with its env workers as actors of a real Ray runtime.

One node (``ray.init`` with 2 CPUs): a few updates give a checkpoint and an ONNX, and the same
weights as the in-process vector env with the same seed (results gathered by worker index).
Two nodes on this machine (Ray's ``cluster_utils.Cluster``): the node hosting an env worker
is killed mid-run, Ray restarts the actor on the other node, and training finishes with the
restart counted in metrics.csv.
"""

from __future__ import annotations

import csv
import importlib
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from functools import partial
from pathlib import Path

import onnxruntime as ort
import pytest
import torch

pytest.importorskip("pybullet")
ray = pytest.importorskip("ray", reason="ray is not installed: pip install -e '.[cluster]'")

from jetbot_rt.train.hyperparams import PPOArgs  # noqa: E402
from jetbot_rt.train.ppo import train  # noqa: E402

NUM_STEPS = 32


def small_run(out: Path, updates: int, **kwargs) -> PPOArgs:
    # One epoch of two minibatches: the Ray side is what these tests are about.
    return PPOArgs(num_envs=2, num_steps=NUM_STEPS, total_timesteps=2 * NUM_STEPS * updates,
                   out=str(out), seed=5, progress=False, checkpoint_every=1, update_epochs=1,
                   num_minibatches=2, **kwargs)


def metrics(out: Path) -> list[dict[str, str]]:
    with (out / "metrics.csv").open() as handle:
        return list(csv.DictReader(handle))


def test_without_ray_flag_ray_is_never_imported():
    code = ("import sys, jetbot_rt.train.cli, jetbot_rt.train.ppo; "
            "sys.exit('ray' in sys.modules)")
    assert subprocess.run([sys.executable, "-c", code], timeout=120).returncode == 0


def test_a_bad_ray_address_is_one_line_and_exit_2(tmp_path, capsys):
    from jetbot_rt.train.cli import main

    with socket.socket() as unused:  # a port nothing listens on
        unused.bind(("127.0.0.1", 0))
        port = unused.getsockname()[1]
    for address, needle in ((f"127.0.0.1:{port}", "no Ray head answers there"),
                            ("nonsense", "expected local, auto, HOST:PORT")):
        assert main(["train", "--ray", address, "--out", str(tmp_path / "x")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and needle in err[0], err
    assert not ray.is_initialized()


def descendants_named(title: str) -> list[int]:
    """Processes below this one whose command line starts with ``title`` (Ray names an actor's
    process ``ray::ClassName``)."""
    parents: dict[int, int] = {}
    for entry in Path("/proc").iterdir():
        try:
            stat = (entry / "stat").read_text()
            parents[int(entry.name)] = int(stat.rsplit(")", 1)[1].split()[1])
        except (ValueError, OSError):
            continue
    found = []
    for pid in parents:
        ancestor = parents.get(pid)
        while ancestor and ancestor != os.getpid():
            ancestor = parents.get(ancestor)
        if ancestor:
            try:
                if (Path("/proc") / str(pid) / "cmdline").read_bytes().startswith(title.encode()):
                    found.append(pid)
            except OSError:
                pass
    return found


@pytest.fixture(scope="class")
def one_node():
    """Ray on this machine with 2 CPUs, shared by the tests of one class (the two-node test
    needs it gone)."""
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


class TestOneNode:
    def test_trains_and_matches_the_in_process_run(self, tmp_path, one_node):
        summary = train(small_run(tmp_path / "ray", 2, ray="local", workers=2))
        out = Path(summary["policy"]).parent
        assert summary["global_step"] == 2 * 2 * NUM_STEPS
        rows = metrics(out)
        assert [r["global_step"] for r in rows] == ["64", "128"]
        assert [r["worker_restarts"] for r in rows] == ["0", "0"]
        session = ort.InferenceSession(summary["policy"], providers=["CPUExecutionProvider"])
        assert session.get_modelmeta().custom_metadata_map["jetbot_rt.task"] == "forward"

        local = train(small_run(tmp_path / "local", 2, workers=0))
        ray_state = torch.load(summary["checkpoint"], weights_only=True)["model"]
        local_state = torch.load(local["checkpoint"], weights_only=True)["model"]
        assert ray_state.keys() == local_state.keys()
        for name, tensor in ray_state.items():
            assert torch.equal(tensor, local_state[name]), name


    def test_sweep_trains_each_seed_and_writes_one_table(self, tmp_path, one_node):
        from jetbot_rt.train.sweep import COLUMNS, sweep

        out = tmp_path / "sweep"
        quick = tmp_path / "quick.toml"  # one rollout, one epoch: the sweep is the point
        quick.write_text("[train]\nnum_steps = 64\nupdate_epochs = 1\n")
        rows = sweep("forward", out, timesteps=64, num_envs=1, seeds=[4, 7],
                     configs=[str(quick)], eval_episodes=1)
        assert [(r["trial"], r["seed"]) for r in rows] == [("quick-seed4", 4),
                                                           ("quick-seed7", 7)]
        for row in rows:
            assert row["global_step"] == 64 and 0.0 <= row["eval_success_rate"] <= 1.0
            assert (out / row["trial"] / "policy.onnx").stat().st_size > 0
            assert (out / row["trial"] / "checkpoint.pt").stat().st_size > 0
        with (out / "sweep.csv").open() as handle:
            table = list(csv.DictReader(handle))
        assert tuple(table[0]) == COLUMNS and [r["seed"] for r in table] == ["4", "7"]
        # The two seeds trained different networks.
        first, second = (torch.load(out / r["trial"] / "checkpoint.pt", weights_only=True)["model"]
                         for r in rows)
        assert any(not torch.equal(first[k], second[k]) for k in first)


    def test_a_worker_that_cannot_build_its_envs_is_one_usage_error(self, one_node):
        from jetbot_rt.errors import UsageError
        from jetbot_rt.train.ray_workers import RayVectorEnv

        with pytest.raises(UsageError, match=r"could not start \(ModuleNotFoundError: No module "
                                              r"named 'pybullet_on_no_node'\)") as caught:
            # an env factory as a node without the sim extra runs it
            RayVectorEnv([partial(importlib.import_module, "pybullet_on_no_node")], workers=1)
        assert "\n" not in str(caught.value)

    def test_workers_lost_beyond_restarts_is_one_line_exit_75_and_a_checkpoint(
            self, tmp_path, one_node, capsys):
        from jetbot_rt.train.cli import main

        out = tmp_path / "lost"
        argv = ["train", "--ray", "--workers", "2", "--num-envs", "2", "--num-steps", "32",
                "--timesteps", "100000", "--update-epochs", "1", "--ray-max-restarts", "0",
                "--out", str(out), "--no-progress"]
        result: dict = {}
        trainer = threading.Thread(target=lambda: result.update(rc=main(argv)), daemon=True)
        trainer.start()
        deadline = time.monotonic() + 300
        while not (out / "metrics.csv").exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        workers = descendants_named("ray::EnvWorker")
        assert workers, "no env worker process found"
        os.kill(workers[0], signal.SIGKILL)
        trainer.join(timeout=300)
        assert result.get("rc") == 75, result
        err = capsys.readouterr().err
        assert "Traceback" not in err
        last = err.strip().splitlines()[-1]
        assert last.startswith("jetbot-train train: error: Ray env worker") and "died" in last
        assert last.endswith("--resume") and str(out / "checkpoint.pt") in last
        state = torch.load(out / "checkpoint.pt", weights_only=True)
        assert state["global_step"] >= 64 and (out / "policy.onnx").stat().st_size > 0


def test_a_killed_worker_node_does_not_end_the_run(tmp_path, capfd):
    from ray.cluster_utils import Cluster

    # Fast node-death detection: the default health check takes ~15 s to declare it.
    fast = {"health_check_initial_delay_ms": 0, "health_check_period_ms": 500,
            "health_check_failure_threshold": 2}
    # Two actors of one CPU each on two one-CPU nodes: one must land on the victim (with a
    # two-CPU head both could land there and nothing would be killed: seen in CI). A fresh
    # node, added after the kill, gives the restarted actor room. Ray adds nodes only from
    # the main thread, so training runs in a thread of its own.
    cluster = Cluster(initialize_head=True, head_node_args={
        "num_cpus": 1, "include_dashboard": False, "_system_config": fast})
    victim = cluster.add_node(num_cpus=1)
    ray.init(address=cluster.address, log_to_driver=False)
    out = tmp_path / "run"
    killed: list[float] = []
    result: dict = {}

    def training() -> None:
        try:
            result["summary"] = train(small_run(out, 3, ray="auto", workers=2))
        except BaseException as exc:  # reported by the assertion below
            result["error"] = exc

    try:
        cluster.wait_for_nodes()
        trainer = threading.Thread(target=training, daemon=True)
        trainer.start()
        deadline = time.monotonic() + 300
        while (not (out / "metrics.csv").exists() and trainer.is_alive()
               and time.monotonic() < deadline):
            time.sleep(0.05)
        if trainer.is_alive():
            cluster.remove_node(victim, allow_graceful=False)
            killed.append(time.monotonic())
            cluster.add_node(num_cpus=1)
        trainer.join(timeout=300)
    finally:
        ray.shutdown()
        cluster.shutdown()
    assert "error" not in result, result.get("error")
    summary = result["summary"]
    assert killed, "the worker node was never killed"
    rows = metrics(out)
    assert [r["global_step"] for r in rows] == ["64", "128", "192"]
    assert rows[0]["worker_restarts"] == "0"
    assert int(rows[-1]["worker_restarts"]) >= 1
    assert Path(summary["policy"]).stat().st_size > 0
    assert Path(summary["checkpoint"]).stat().st_size > 0
    assert "lost; restart 1 of at most" in capfd.readouterr().err


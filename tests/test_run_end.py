"""Ctrl-C at the end of a training run: in the workers' clean close it ends them instead, in
the export it is acted on after the policy is written; either way the run ends as a Ctrl-C
does (``Interrupted``: exit 130 and the resume command), with ``policy.onnx``."""

from __future__ import annotations

import multiprocessing
import os
import signal
from typing import Any

import pytest

from jetbot_rt.train.run_end import interrupt_noted

pytest.importorskip("pybullet")


@pytest.fixture(autouse=True)
def python_ctrl_c():
    """SIGINT as a terminal's Ctrl-C reaches Python (an earlier test in this worker may have
    left another handler, which the signals sent here must not reach)."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def _ctrl_c() -> None:
    os.kill(os.getpid(), signal.SIGINT)


def _ends_interrupted_with_the_policy(train, args, out, escaped: str) -> Any:
    """``train(args)`` raises ``Interrupted`` (not a bare KeyboardInterrupt: ``escaped``
    says where one would have come from) and ``out`` holds the policy; the summary."""
    from jetbot_rt.train.run_dir import Interrupted

    with pytest.raises(Interrupted) as stop:
        try:
            train(args)
        except KeyboardInterrupt:
            pytest.fail(escaped)
    assert (out / "policy.onnx").stat().st_size > 0
    return stop.value.summary


def test_ctrl_c_in_the_export_is_acted_on_after_the_policy_is_written(tmp_path, monkeypatch):
    from jetbot_rt.train import dagger
    from jetbot_rt.train.hyperparams import dagger_args
    from jetbot_rt.train.run_dir import Interrupted, RunDirectory

    export = RunDirectory.export_policy

    def interrupted_export(self, *args, **kwargs):
        _ctrl_c()
        return export(self, *args, **kwargs)

    monkeypatch.setattr(RunDirectory, "export_policy", interrupted_export)
    args = dagger_args("seek", {"iterations": 1, "steps_per_iteration": 10,
                                "train_samples": 32, "num_envs": 1, "workers": 0,
                                "out": str(tmp_path), "progress": False})
    with pytest.raises(Interrupted) as stop:
        dagger.train(args)
    assert stop.value.summary["updates"] == 1
    assert (tmp_path / "policy.onnx").stat().st_size > 0
    assert (tmp_path / "learning_curve.png").stat().st_size > 0


def test_ctrl_c_while_a_clean_close_waits_on_the_workers_ends_them(tmp_path, monkeypatch):
    from jetbot_rt.train import ppo, rollout
    from jetbot_rt.train.hyperparams import PPOArgs
    from jetbot_rt.train.run_dir import Interrupted

    close = rollout.close_vector_env
    closes = []

    def interrupted_close(envs, interrupted):
        closes.append(interrupted)
        if not interrupted:
            raise KeyboardInterrupt  # as if it came while gymnasium waits on the workers
        close(envs, interrupted)

    monkeypatch.setattr(rollout, "close_vector_env", interrupted_close)
    args = PPOArgs(num_envs=1, num_steps=16, total_timesteps=16, update_epochs=1,
                   out=str(tmp_path), progress=False)
    with pytest.raises(Interrupted):
        ppo.train(args)
    assert closes == [False, True]
    assert multiprocessing.active_children() == []
    assert (tmp_path / "policy.onnx").stat().st_size > 0


def test_a_worker_gone_by_the_end_of_a_finished_run_costs_no_policy(tmp_path, monkeypatch,
                                                                      capsys):
    """A worker killed after the last update (the OOM killer, a crash in its env's close):
    gymnasium's clean close meets a broken pipe; the others are ended, the policy written."""
    from jetbot_rt.train import ppo
    from jetbot_rt.train.hyperparams import PPOArgs

    save = ppo._Run.save

    def save_then_lose_a_worker(self):
        save(self)
        if self.progress.global_step >= self.options.total_timesteps:
            worker = self.source.envs.unwrapped.processes[0]
            os.kill(worker.pid, signal.SIGKILL)
            worker.join()

    monkeypatch.setattr(ppo._Run, "save", save_then_lose_a_worker)
    args = PPOArgs(num_envs=2, num_steps=16, total_timesteps=32, update_epochs=1,
                   out=str(tmp_path), progress=False)
    assert ppo.train(args)["global_step"] == 32
    assert "an env worker was gone at the end" in capsys.readouterr().err
    assert multiprocessing.active_children() == []
    assert (tmp_path / "policy.onnx").stat().st_size > 0


def test_a_second_ctrl_c_while_the_files_are_written_raises_and_a_copy_does_not(
        monkeypatch):
    from jetbot_rt.train import run_end

    with interrupt_noted() as noted:
        _ctrl_c()
        _ctrl_c()  # within DUPLICATE_S: the first's copy
    assert noted()
    monkeypatch.setattr(run_end, "DUPLICATE_S", 0.0)
    with pytest.raises(KeyboardInterrupt), interrupt_noted() as noted:
        _ctrl_c()
        assert noted()
        _ctrl_c()
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_where_ctrl_c_is_ignored_it_stays_ignored():
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)  # a shell's background job
    try:
        with interrupt_noted() as noted:
            _ctrl_c()
        assert not noted()
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, previous)


@pytest.mark.parametrize("algo", ["ppo", "dagger"])
def test_timeouts_copy_of_the_ctrl_c_during_the_save_still_ends_with_the_policy(
        tmp_path, monkeypatch, algo):
    """``timeout -s INT`` signals the trainer, then its process group: a second SIGINT
    microseconds after the first, here sent from inside the save the first one started."""
    from jetbot_rt.train import dagger, ppo
    from jetbot_rt.train.hyperparams import PPOArgs, dagger_args

    trainer = ppo if algo == "ppo" else dagger
    step = "update" if algo == "ppo" else "iteration"
    save, work = trainer._Run.save, getattr(trainer._Run, step)
    saves = []

    def interrupted_step(self, *args):
        result = work(self, *args)
        _ctrl_c()  # the first SIGINT, at the end of the first update (iteration)
        return result

    def save_with_the_copy(self):
        saves.append(self.progress.update)
        if len(saves) == 1:
            _ctrl_c()
        save(self)

    monkeypatch.setattr(trainer._Run, step, interrupted_step)
    monkeypatch.setattr(trainer._Run, "save", save_with_the_copy)
    if algo == "ppo":
        args = PPOArgs(num_envs=1, num_steps=16, total_timesteps=64, update_epochs=1,
                       workers=0, out=str(tmp_path), progress=False)
    else:
        args = dagger_args("seek", {"iterations": 3, "steps_per_iteration": 10,
                                    "train_samples": 32, "num_envs": 1, "workers": 0,
                                    "out": str(tmp_path), "progress": False})
    summary = _ends_interrupted_with_the_policy(
        trainer.train, args, tmp_path, "the copy of the Ctrl-C ended the run in its save")
    assert summary["updates"] == 1 and saves == [1]
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_a_ctrl_c_after_the_copys_moment_still_raises(monkeypatch):
    from jetbot_rt.train import run_end

    with run_end.duplicates_ignored():
        _ctrl_c()  # a copy: ignored
    monkeypatch.setattr(run_end, "DUPLICATE_S", 0.0)
    with pytest.raises(KeyboardInterrupt), run_end.duplicates_ignored():
        _ctrl_c()
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_a_second_ctrl_c_in_the_export_after_a_first_is_noted_and_the_policy_written(
        tmp_path, monkeypatch):
    """After the loop's Ctrl-C the export is guarded as ever: a second SIGINT there (later
    than a copy's moment) is noted, and the policy is still written."""
    from jetbot_rt.train import ppo, run_end
    from jetbot_rt.train.hyperparams import PPOArgs
    from jetbot_rt.train.run_dir import RunDirectory

    update, export = ppo._Run.update, RunDirectory.export_policy

    def interrupted_update(self):
        row = update(self)
        _ctrl_c()
        return row

    def export_with_a_second(self, *args, **kwargs):
        monkeypatch.setattr(run_end, "DUPLICATE_S", 0.0)
        _ctrl_c()
        return export(self, *args, **kwargs)

    monkeypatch.setattr(ppo._Run, "update", interrupted_update)
    monkeypatch.setattr(RunDirectory, "export_policy", export_with_a_second)
    args = PPOArgs(num_envs=1, num_steps=16, total_timesteps=64, update_epochs=1, workers=0,
                   out=str(tmp_path), progress=False)
    _ends_interrupted_with_the_policy(ppo.train, args, tmp_path,
                                      "a Ctrl-C in the export ended the run")


def test_a_copy_while_the_workers_are_ended_after_the_last_update_costs_no_policy(
        tmp_path, monkeypatch):
    """``timeout``'s pair landing in a finished run's clean close: the first ends the workers,
    its copy does not cut that short."""
    from jetbot_rt.train import ppo, rollout

    close = rollout.close_vector_env

    def close_with_a_pair(envs, interrupted):
        if not interrupted:
            raise KeyboardInterrupt  # the first, while gymnasium waits on the workers
        _ctrl_c()  # its copy
        close(envs, interrupted)

    monkeypatch.setattr(rollout, "close_vector_env", close_with_a_pair)
    from jetbot_rt.train.hyperparams import PPOArgs

    args = PPOArgs(num_envs=1, num_steps=16, total_timesteps=16, update_epochs=1,
                   out=str(tmp_path), progress=False)
    _ends_interrupted_with_the_policy(ppo.train, args, tmp_path,
                                      "the copy ended the run while its workers were ended")
    assert multiprocessing.active_children() == []

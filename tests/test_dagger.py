"""DAgger for seek: the privileged expert (pure control law, then driving the real sim with
randomization on), the student's regression, and ``jetbot-train train --algo dagger`` end to
end (checkpoint, ONNX the runtime's evaluation loads, metrics, curve)."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest
import torch
from plain_sim import plain_config, plain_sim_file
from train_runner import train_here

from jetbot_rt.train.expert import Expert

pytest.importorskip("pybullet")

EXPERT = Expert()


def test_expert_turns_toward_the_goal_and_stops_short_of_it():
    ahead_left = EXPERT.act(np.array([0.0, 0.0, 0.0]), np.array([0.6, 0.1]), 0.0)
    ahead_right = EXPERT.act(np.array([0.0, 0.0, 0.0]), np.array([0.6, -0.1]), 0.0)
    assert ahead_left[1] > ahead_left[0] > 0 and ahead_right[0] > ahead_right[1] > 0
    for side in (0.5, -0.5):  # out of view: turns left backing away, whichever side it is on
        out_of_view = EXPERT.act(np.array([0.0, 0.0, 0.0]), np.array([0.2, side]), 0.0)
        assert out_of_view.tolist() == pytest.approx([EXPERT.search_left, EXPERT.search_right])
        assert EXPERT.search_left < 0 < EXPERT.search_right
    behind = EXPERT.act(np.array([0.0, 0.0, 0.0]), np.array([-0.5, 0.01]), 0.0)
    straight = EXPERT.act(np.array([0.0, 0.0, math.pi / 2]), np.array([0.0, 1.0]), 0.0)
    assert straight.tolist() == pytest.approx([1.0, 1.0])
    near = EXPERT.act(np.array([0.0, 0.0, 0.0]), np.array([EXPERT.stop_distance - 0.01, 0]), 0)
    assert near.tolist() == [0.0, 0.0]
    # closer than the back-off distance (the block below the camera's view): backs away slowly
    blind = EXPERT.act(np.array([0.0, 0.0, 0.0]), np.array([EXPERT.backoff_distance - 0.005, 0]),
                       0)
    assert blind.tolist() == pytest.approx([EXPERT.backoff, EXPERT.backoff])
    assert EXPERT.backoff < 0 < EXPERT.backoff_distance < EXPERT.stop_distance
    lead = Expert(stop_lead=0.15)
    fast = lead.act(np.array([0.0, 0.0, 0.0]), np.array([lead.stop_distance + 0.02, 0]), 0.3)
    assert fast.tolist() == [0.0, 0.0]  # with a lead, moving: stops earlier
    for action in (ahead_left, ahead_right, behind, straight):
        assert np.all(np.abs(action) <= 1.0)


def test_expert_succeeds_on_randomized_seek_episodes():
    """It reads only the state in ``info``; randomization (gains, dead-band, latencies) on."""
    from jetbot_rt.train.expert import evaluate_expert

    assert evaluate_expert(3) == 1.0


def test_regression_fits_the_labels():
    from jetbot_rt.train.dagger import Dataset, regress
    from jetbot_rt.train.hyperparams import dagger_args
    from jetbot_rt.train.model import ActorCritic

    args = dagger_args("seek", {"train_samples": 1024, "batch_size": 32, "learning_rate": 3e-3})
    rng = np.random.default_rng(0)
    data = Dataset((56, 56, 3))
    frames = rng.integers(0, 256, (8, 56, 56, 3), dtype=np.uint8)
    frames[:4, :, :, 0] = 255  # red-ish frames: drive; the others: stop
    labels = np.array([[0.8, 0.9]] * 4 + [[0.0, 0.0]] * 4, dtype=np.float32)
    data.add(frames, labels)
    torch.manual_seed(0)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # two threads on two busy cores spin more than they compute
    model = ActorCritic(args.model)
    optimizer = torch.optim.Adam(model.parameters(), lr=args.learning_rate)
    try:
        regress(model, optimizer, data, args, rng)
    finally:
        torch.set_num_threads(threads)
    with torch.no_grad():
        mu = model(torch.from_numpy(frames))[0].numpy()
    assert np.abs(mu - labels).max() < 0.1


def test_stops_and_turns_on_the_spot_weigh_their_own_weights():
    from jetbot_rt.train.dagger import label_weights
    from jetbot_rt.train.hyperparams import dagger_args

    args = dagger_args("avoid", {"stop_weight": 4.0, "turn_weight": 3.0})
    labels = np.array([[0.8, 0.9], [0.0, 0.0], [-0.5, -0.1], [-0.9, 0.9], [0.3, -0.2],
                       [0.0, 0.7]], dtype=np.float32)
    assert label_weights(labels, args).tolist() == [1.0, 4.0, 4.0, 3.0, 3.0, 1.0]
    assert dagger_args("avoid").turn_weight == 1.0  # off unless asked for


def test_mirror_flips_only_the_chosen_frames_and_swaps_their_wheels():
    from jetbot_rt.train.dagger import mirror

    x = torch.arange(2 * 3 * 2 * 4, dtype=torch.float32).reshape(2, 3, 2, 4)
    labels = torch.tensor([[0.2, 0.9], [1.0, -0.5]])
    flipped, swapped = mirror(x, labels, np.array([False, True]))
    assert torch.equal(flipped[0], x[0]) and torch.equal(swapped[0], labels[0])
    assert torch.equal(flipped[1, :, :, 0], x[1, :, :, 3])  # columns reversed, rows kept
    assert torch.equal(flipped[1, :, 0], x[1, :, 0].flip(-1))
    assert swapped[1].tolist() == [-0.5, 1.0]
    assert torch.equal(x[1, 0, 0], torch.tensor([24.0, 25.0, 26.0, 27.0]))  # input untouched


def test_regression_with_mirror_learns_the_mirrored_label_of_symmetric_frames_only():
    """Two frames, each lit on one side: the left-lit one labelled (left, right) = (0.2, 0.8)
    and symmetric, so its mirror (lit on the right) learns (0.8, 0.2); the right-lit one is
    labelled (0.5, 0.5) and not symmetric, so its label is never swapped."""
    from jetbot_rt.train.dagger import Dataset, regress
    from jetbot_rt.train.hyperparams import dagger_args
    from jetbot_rt.train.model import ActorCritic

    args = dagger_args("avoid", {"train_samples": 2048, "batch_size": 32,
                                 "learning_rate": 3e-3, "photometric_jitter": 0.0,
                                 "mirror": 0.5})
    frames = np.zeros((3, 56, 56, 3), dtype=np.uint8)
    frames[0, :, :28] = 255  # lit on the left
    frames[1, :, 28:, 1] = 255  # green on the right, never mirrored
    frames[2, :, 28:, 1] = 255
    frames[2, :, 28:, 0] = 255  # yellow on the right: frame 0 in a mirror, and only that
    data = Dataset((56, 56, 3))
    data.add(frames[:2], np.array([[0.2, 0.8], [0.5, 0.5]], dtype=np.float32),
             np.array([True, False]))
    torch.manual_seed(0)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    model = ActorCritic(args.model)
    optimizer = torch.optim.Adam(model.parameters(), lr=args.learning_rate)
    try:
        regress(model, optimizer, data, args, np.random.default_rng(0))
    finally:
        torch.set_num_threads(threads)
    mirrored = frames[0, :, ::-1].copy()
    with torch.no_grad():
        mu = model(torch.from_numpy(np.stack([frames[0], frames[1], mirrored])))[0].numpy()
    assert np.abs(mu - [[0.2, 0.8], [0.5, 0.5], [0.8, 0.2]]).max() < 0.1


def test_avoid_expert_is_symmetric_in_the_open_and_mirrors_there():
    from jetbot_rt.tasks.avoid import AvoidExpert

    expert, rng = AvoidExpert(), np.random.default_rng(5)
    open_ways = 0
    for _ in range(200):
        ranges = rng.uniform(0.1, 1.0, 9)
        info, mirrored = {"ranges": ranges}, {"ranges": ranges[::-1].copy()}
        if expert.symmetric(info):
            open_ways += 1
            assert expert.symmetric(mirrored)
            assert np.allclose(expert.label(mirrored), expert.label(info)[::-1], atol=1e-6)
        else:  # something close ahead: the turn is always left, whichever the side
            assert expert.urgency(ranges) > 0
    assert 20 < open_ways < 180
    blocked = {"ranges": np.full(9, 0.1)}
    assert not expert.symmetric(blocked)
    assert np.allclose(expert.label(blocked), [-0.9, 0.9])


def test_expert_options_left_alone_keep_a_task_experts_own_defaults():
    import dataclasses

    from jetbot_rt.tasks.avoid import Avoid, AvoidExpert
    from jetbot_rt.train.dagger import expert_settings
    from jetbot_rt.train.expert import task_expert
    from jetbot_rt.train.hyperparams import DAggerArgs

    class SlowAvoid(Avoid):  # a user's task whose expert has its own min_forward
        def expert(self) -> AvoidExpert:
            return AvoidExpert(min_forward=0.6)

    defaults = DAggerArgs(task="avoid")
    assert expert_settings(defaults) == {}
    assert task_expert(SlowAvoid(), expert_settings(defaults)).min_forward == 0.6
    assert task_expert("avoid", expert_settings(defaults)).min_forward == 0.75
    changed = dataclasses.replace(defaults, min_forward=0.9, search_left=0.2)
    assert expert_settings(changed) == {"min_forward": 0.9, "search_left": 0.2}
    assert task_expert(SlowAvoid(), expert_settings(changed)).min_forward == 0.9
    as_seek = dataclasses.replace(defaults, min_forward=0.75)  # given, though seek's default
    assert task_expert(SlowAvoid(), expert_settings(as_seek)).min_forward == 0.75


def test_dataset_keeps_every_added_frame_in_order_as_it_grows():
    from jetbot_rt.train.dagger import Dataset

    rng = np.random.default_rng(3)
    data = Dataset((4, 4, 3))
    batches = [(rng.integers(0, 256, (n, 4, 4, 3), dtype=np.uint8),
                rng.standard_normal((n, 2)).astype(np.float32)) for n in (5, 0, 1, 17, 3, 40)]
    flags = [rng.random(len(labels)) < 0.5 if i % 2 else None
             for i, (_, labels) in enumerate(batches)]
    for (frames, labels), symmetric in zip(batches, flags):
        data.add(frames, labels, symmetric)
    assert len(data) == 66
    assert np.array_equal(data.frames, np.concatenate([f for f, _ in batches]))
    assert np.array_equal(data.labels, np.concatenate([la for _, la in batches]))
    expected = [np.zeros(len(la), bool) if s is None else s
                for (_, la), s in zip(batches, flags)]
    assert np.array_equal(data.symmetric, np.concatenate(expected))
    assert data.symmetric.any() and not data.symmetric.all()


def test_photometric_jitter_scales_each_frame_within_its_range():
    from jetbot_rt.train.dagger import jitter

    rng = np.random.default_rng(0)
    x = torch.full((400, 3, 8, 8), 0.5)
    x[:, :, :4] = 0.25  # contrast shows as the spread between the halves
    out = jitter(x, 0.2, rng)
    assert out.shape == x.shape and out.min() >= 0.0 and out.max() <= 1.0
    gain = out[:, :, 4:].mean((2, 3)) / 0.5  # per frame and channel
    assert gain.min() < 0.85 and gain.max() > 1.15  # brightness, contrast, channel together
    assert gain.min() > 0.8 * 0.8 * 0.9 - 0.1 and gain.max() < 1.2 * 1.2 * 1.1 + 0.1
    channel_spread = (gain / gain.mean(1, keepdim=True)).std()
    assert channel_spread > 0.02  # the channels are scaled apart, not together
    assert torch.equal(jitter(x, 0.0, rng), x)


def test_learning_rate_falls_geometrically_to_the_final_one():
    from jetbot_rt.train.dagger import learning_rate_at
    from jetbot_rt.train.hyperparams import dagger_args

    args = dagger_args("seek", {"iterations": 3, "learning_rate": 1e-3,
                                "final_learning_rate": 1e-5})
    assert [learning_rate_at(args, i) for i in range(3)] == pytest.approx([1e-3, 1e-4, 1e-5])
    constant = dagger_args("seek", {"iterations": 3})
    assert {learning_rate_at(constant, i) for i in range(3)} == {constant.learning_rate}


def test_train_algo_dagger_writes_the_run_directory(tmp_path, capsys):
    out = tmp_path / "seek"
    result = train_here(capsys, "train", "--task", "seek", "--algo", "dagger", "--iterations", "2",
                       "--steps-per-iteration", "20", "--train-samples", "64", "--beta", "1",
                       "--num-envs", "1", "--workers", "0", "--out", str(out), "--no-progress",
                       "--snapshots", "2", "--config", str(plain_sim_file(tmp_path)))
    assert result.returncode == 0, result.stderr
    for name in ("checkpoint.pt", "policy.onnx", "metrics.csv", "learning_curve.png",
                 "policy_2.onnx"):
        assert (out / name).stat().st_size > 0, name
    with (out / "metrics.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert [r["iteration"] for r in rows] == ["1", "2"]
    assert rows[0]["expert_success_rate"] and not rows[0]["success_rate"]  # expert drove
    assert int(rows[1]["dataset"]) > int(rows[0]["dataset"]) >= 20
    state = torch.load(out / "checkpoint.pt", weights_only=True)
    assert (state["task"], state["algo"], state["update"]) == ("seek", "dagger", 2)
    from jetbot_rt.config.sections import Config
    from jetbot_rt.train.evaluate import load_policy

    policy = load_policy(out / "policy.onnx", Config())
    assert policy.metadata["jetbot_rt.task"] == "seek" and policy.max_speed == 0.5


def test_dagger_needs_an_expert_and_refuses_other_algorithms_flags(tmp_path, capsys):
    forward = train_here(capsys, "train", "--task", "forward", "--algo", "dagger", "--out",
                        str(tmp_path / "f"))
    assert forward.returncode == 2 and "has no expert for DAgger" in forward.stderr
    mixed = train_here(capsys, "train", "--task", "seek", "--gamma", "0.9", "--out",
                       str(tmp_path / "m"))
    assert mixed.returncode == 2
    assert mixed.stderr.strip() == ("jetbot-train train: error: --gamma is not an option of "
                                    "--algo dagger")


def test_ctrl_c_saves_exports_and_resumes_from_the_iteration(tmp_path, monkeypatch):
    """Ctrl-C (a KeyboardInterrupt in the regression of iteration 2) writes the checkpoint of
    the last finished iteration, the ONNX and the curve; --resume goes on from there."""
    from jetbot_rt.train import dagger
    from jetbot_rt.train.hyperparams import dagger_args
    from jetbot_rt.train.run_dir import Interrupted

    args = dagger_args("seek", {"iterations": 2, "steps_per_iteration": 10,
                                       "train_samples": 32, "num_envs": 1, "workers": 0,
                                       "beta": 1.0, "out": str(tmp_path), "progress": False})
    args.config = plain_config()  # the looks are not what a Ctrl-C saves
    real = dagger.regress
    calls = []

    def interrupted_second_time(*a, **k):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(dagger, "regress", interrupted_second_time)
    with pytest.raises(Interrupted) as stop:
        dagger.train(args)
    assert stop.value.summary["updates"] == 1
    assert torch.load(tmp_path / "checkpoint.pt", weights_only=True)["update"] == 1
    assert (tmp_path / "policy.onnx").stat().st_size > 0
    assert (tmp_path / "learning_curve.png").stat().st_size > 0
    monkeypatch.setattr(dagger, "regress", real)
    args.resume = True
    assert dagger.train(args)["updates"] == 2
    with (tmp_path / "metrics.csv").open() as handle:
        assert [r["iteration"] for r in csv.DictReader(handle)] == ["1", "2"]


def test_the_expert_labels_the_state_the_frame_shows():
    """With a camera latency, a frame at tick n shows the world of tick n - latency / period:
    the expert's label of it reads that tick's info (the reset's before the episode got there);
    --expert-sees now reads tick n's."""
    from jetbot_rt.config.sections import from_dict
    from jetbot_rt.train.dagger_sampler import LabelSampler
    from jetbot_rt.train.env import JetbotEnv
    from jetbot_rt.train.hyperparams import ModelConfig
    from jetbot_rt.train.model import ActorCritic

    class Recorder:  # an expert that returns the sim_time of the info it was given
        reads = ("sim_time",)

        def label(self, info):
            return np.array([info["sim_time"], 0.0], dtype=np.float32)

    config = from_dict({"sim": {"camera_latency": 0.1, "lens": "pinhole"},
                        "randomize": {"enabled": False}})
    env = JetbotEnv("seek", config)
    sampler = LabelSampler(env, ModelConfig(), 0)
    weights = {k: v.detach().numpy() for k, v in ActorCritic(ModelConfig()).state_dict().items()}
    ticks = round(0.1 / env.period)
    try:
        for sees, lag in (("frame", ticks), ("now", 0)):
            sampler.reset(seed=0)
            labels = sampler.collect_labelled(weights, 20, (1, 0), 1.0, 0.0, Recorder(),
                                              sees)["labels"][:20, 0]
            times = np.arange(20) * env.period
            assert labels == pytest.approx(np.maximum(times - lag * env.period, 0.0), abs=1e-6)
    finally:
        env.close()

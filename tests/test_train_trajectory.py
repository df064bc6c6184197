"""No seam between training and the runtime: one ONNX policy, driven from the nominal start
by the Gymnasium env and by ``jetbot-rt run --backend sim``, gives the same trajectory; also
in a randomized episode, whose draw the runtime gets as the [sim] table of its config."""

from __future__ import annotations

import numpy as np
import pytest
from runner import run_cli

from jetbot_rt.config.sections import Config, from_dict
from jetbot_rt.runtime.policy import bundled_policy_path
from jetbot_rt.train.env import JetbotEnv
from jetbot_rt.train.evaluate import load_policy

pytest.importorskip("pybullet")

DURATION_S = 2.0  # 60 ticks on an idle machine
RANDOMIZED_SEED = 4


def _env_trajectory(env: JetbotEnv, policy, ticks: int, seed: int) -> tuple[np.ndarray, ...]:
    """Tick k of the runtime: frame after k world steps -> mu -> duties -> one step -> pose."""
    obs, _ = env.reset(seed=seed, options={"start_noise": False})
    env_mu, env_cmd, env_pose = [], [], []
    for _ in range(ticks):
        mu = policy.infer(obs)
        obs, _, _, _, info = env.step(mu)
        env_mu.append(mu)
        env_cmd.append(info["duty"])
        env_pose.append(info["pose"])
    return np.array(env_mu), np.array(env_cmd), np.array(env_pose)


@pytest.mark.skipif(not bundled_policy_path().exists(), reason="no bundled policy")
@pytest.mark.parametrize("randomized", [False, True], ids=["ideal", "randomized"])
def test_env_and_runtime_give_the_same_trajectory(tmp_path, monkeypatch, randomized):
    monkeypatch.setenv("JETBOT_RT_RUNTIME_DIR", str(tmp_path))
    policy_path = bundled_policy_path()
    config = Config()
    policy = load_policy(policy_path, config, single_thread=False)
    size = (policy.spec.width, policy.spec.height)  # the runtime renders at the policy's size
    # The trajectory is in simulated time; on a loaded machine a slow render must not trip
    # the watchdog or the frame-age check (their own tests cover them).
    loop = "[loop]\nwatchdog_timeout = 2.0\nmax_frame_age = 2.0\n"
    (tmp_path / "run.toml").write_text(loop)
    args = ["run", "--backend", "sim", "--policy", str(policy_path), "--duration", str(DURATION_S),
            "--config", str(tmp_path / "run.toml")]
    sim_params = None
    if randomized:  # the env draws the episode's [sim]; the runtime replays it from its config
        from jetbot_rt.sim.randomize import sim_toml

        config = from_dict({"randomize": {"deadband": [0.0, 0.05]}})  # below max_speed 0.1
        env = JetbotEnv("forward", config, model_max_speed=policy.max_speed, randomize=True,
                        image_size=size)
        try:
            _, info = env.reset(seed=RANDOMIZED_SEED, options={"start_noise": False})
            sim_params = info["sim_params"]
            (tmp_path / "run.toml").write_text(loop + sim_toml(env.world.sim))
        finally:
            env.close()
        assert sim_params["latency"] > 0 and sim_params["camera_latency"] > 0
        assert sim_params["wheel_gain"] != [1.0, 1.0] and sim_params["image_noise"] > 0
    result = run_cli(args, telemetry=tmp_path / "t.jsonl")
    assert result.returncode == 0, result.stderr
    ticks = result.ticks
    assert len(ticks) >= 30  # the tick count in a wall-clock duration depends on the load

    env = JetbotEnv("forward", config, model_max_speed=policy.max_speed, randomize=randomized,
                    image_size=size)
    try:
        env_mu, env_cmd, env_pose = _env_trajectory(env, policy, len(ticks), RANDOMIZED_SEED)
        if randomized:
            assert env.sim_params == sim_params
    finally:
        env.close()

    rt_mu = np.array([t["mu"] for t in ticks])
    rt_cmd = np.array([t["cmd"] for t in ticks])
    rt_pose = np.array([t["pose"] for t in ticks])
    rt_time = np.array([t["sim_time"] for t in ticks])
    assert rt_time == pytest.approx(np.arange(1, len(ticks) + 1) / 30, abs=1 / 240)
    assert np.max(np.abs(rt_mu - env_mu)) < 1e-4
    assert np.max(np.abs(rt_cmd - env_cmd)) < 1e-5
    assert np.max(np.abs(rt_pose - env_pose)) < 1e-3
    # and it is a real trajectory: the bundled policy drives towards the block (0.06 m/s)
    assert rt_pose[-1][0] - rt_pose[0][0] > 0.03 * len(ticks) / 30


def _seek_policy(tmp_path):
    """The bundled seek policy; before one is bundled, a constant curve with seek metadata."""
    import policy_models

    if bundled_policy_path("seek").exists():
        return bundled_policy_path("seek")
    return policy_models.constant(tmp_path / "seek.onnx", (0.6, 1.0), size=56,
                                  metadata={"jetbot_rt.task": "seek", "jetbot_rt.max_speed": "0.5"})


def test_seek_scene_and_randomized_draw_are_the_same_in_env_and_runtime(tmp_path, monkeypatch):
    """The runtime builds the policy's task's scene from [sim] seed and, with [randomize]
    enabled, draws the [sim] knobs from the same generator after it: the env's
    ``reset(seed=seed, options={"start_noise": False})``, distractors and all."""
    monkeypatch.setenv("JETBOT_RT_RUNTIME_DIR", str(tmp_path))
    policy_path = _seek_policy(tmp_path)
    seed = 7
    toml = ("[loop]\nwatchdog_timeout = 2.0\nmax_frame_age = 2.0\n"
            f"[sim]\nseed = {seed}\n[randomize]\nenabled = true\n")
    (tmp_path / "run.toml").write_text(toml)
    result = run_cli(["run", "--backend", "sim", "--policy", str(policy_path), "--duration",
                      str(DURATION_S), "--config", str(tmp_path / "run.toml")],
                     telemetry=tmp_path / "t.jsonl")
    assert result.returncode == 0, result.stderr
    ticks = result.ticks
    assert len(ticks) >= 30

    config = from_dict({"randomize": {"enabled": True}})
    policy = load_policy(policy_path, config, single_thread=False)
    env = JetbotEnv("seek", config, model_max_speed=policy.max_speed,
                    image_size=(policy.spec.width, policy.spec.height))
    try:
        obs, first = env.reset(seed=seed, options={"start_noise": False})
        assert len(env.scene.pieces) >= 2 and first["sim_params"]["latency"] > 0
        env_pose, env_goal, env_mu = [], [], []
        for _ in ticks:
            mu = policy.infer(obs)
            obs, _, terminated, truncated, info = env.step(mu)
            env_mu.append(mu)
            env_pose.append(info["pose"])
            env_goal.append(info["distance"])
            if terminated or truncated:
                break
    finally:
        env.close()
    n = len(env_mu)
    rt = ticks[:n]
    assert np.max(np.abs(np.array([t["mu"] for t in rt]) - np.array(env_mu))) < 1e-4
    assert np.max(np.abs(np.array([t["pose"] for t in rt]) - np.array(env_pose))) < 1e-3
    goal = np.array([t["goal_distance"] for t in rt])
    assert np.max(np.abs(goal - np.array(env_goal))) < 1e-3  # the same goal, the same draw
    assert np.linalg.norm(np.array(rt[-1]["pose"][:2]) - first["pose"][:2]) > 0.05

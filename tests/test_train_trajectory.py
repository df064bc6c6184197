"""No seam between training and the runtime: one ONNX policy, driven from the nominal start
by the Gymnasium env and by ``jetbot-rt run --backend sim``, gives the same trajectory."""

from __future__ import annotations

import numpy as np
import pytest
from runner import run_cli

from jetbot_rt.config import Config
from jetbot_rt.policy import bundled_policy_path
from jetbot_rt.train.env import JetbotEnv
from jetbot_rt.train.evaluate import load_policy

pytest.importorskip("pybullet")

DURATION_S = 3.0


@pytest.mark.skipif(not bundled_policy_path().exists(), reason="no bundled policy")
def test_env_and_runtime_give_the_same_trajectory(tmp_path, monkeypatch):
    monkeypatch.setenv("JETBOT_RT_RUNTIME_DIR", str(tmp_path))
    policy_path = bundled_policy_path()
    result = run_cli(["run", "--backend", "sim", "--policy", str(policy_path),
                      "--duration", str(DURATION_S)], telemetry=tmp_path / "t.jsonl")
    assert result.returncode == 0, result.stderr
    ticks = result.ticks
    assert len(ticks) >= 0.8 * DURATION_S * 30

    # Tick k of the runtime: frame after k world steps -> mu -> duties -> one step -> pose.
    config = Config()
    policy = load_policy(policy_path, config, single_thread=False)
    env = JetbotEnv("forward", config, model_max_speed=policy.max_speed,
                    image_size=(policy.spec.width, policy.spec.height))
    try:
        obs, _ = env.reset(seed=0, options={"start_noise": False})
        env_mu, env_cmd, env_pose = [], [], []
        for _ in ticks:
            mu = policy.infer(obs)
            obs, _, _, _, info = env.step(mu)
            env_mu.append(mu)
            env_cmd.append(info["duty"])
            env_pose.append(info["pose"])
    finally:
        env.close()

    rt_mu = np.array([t["mu"] for t in ticks])
    rt_cmd = np.array([t["cmd"] for t in ticks])
    rt_pose = np.array([t["pose"] for t in ticks])
    rt_time = np.array([t["sim_time"] for t in ticks])
    assert rt_time == pytest.approx(np.arange(1, len(ticks) + 1) / 30, abs=1 / 240)
    assert np.max(np.abs(rt_mu - np.array(env_mu))) < 1e-4
    assert np.max(np.abs(rt_cmd - np.array(env_cmd))) < 1e-5
    assert np.max(np.abs(rt_pose - np.array(env_pose))) < 1e-3
    # and it is a real trajectory: the bundled policy drives towards the block
    assert rt_pose[-1][0] - rt_pose[0][0] > 0.1

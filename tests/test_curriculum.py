"""Curricula: the schedule (rises on success, never past 1), the difficulty in the env workers'
scenes, evaluation at full difficulty whatever training set, the trainers' metrics and
resume, and a user's task without a curriculum (docs/CURRICULUM.md)."""

from __future__ import annotations

import copy
import csv
import math
import textwrap
from types import SimpleNamespace

import numpy as np
import pytest
from train_runner import train_here

from jetbot_rt.config.sections import Config
from jetbot_rt.tasks import load_task
from jetbot_rt.train.curriculum import COLUMN, Schedule, send
from jetbot_rt.train.hyperparams import dagger_args

pytest.importorskip("pybullet")

TASK_SOURCE = textwrap.dedent("""
    from jetbot_rt.tasks import Block, Scene, Task

    class Mine(Task):
        description = "a user's task without a curriculum"
        episode_steps = 8

        def scene(self, rng, start_noise):
            return Scene((0.0, 0.0, 0.0), (Block((0.5, 0.0), "green", name="goal"),))

        def outcome(self, scene, world):
            return {"is_success": world.distance("goal") < 0.2}
""")


CURRICULUM_TASK_SOURCE = textwrap.dedent("""
    import numpy as np

    from jetbot_rt.tasks import Block, Scene, Task

    class Near(Task):
        description = "a user's task with a curriculum: the goal farther as it gets harder"
        episode_steps = 2
        curriculum = True

        def scene(self, rng, start_noise):
            (x,) = self.between((0.3,), (1.0,))
            return Scene((0.0, 0.0, 0.0), (Block((x, 0.0), "green", name="goal"),))

        def outcome(self, scene, world):
            return {"is_success": True, "goal_x": scene.piece("goal").xy[0]}

        def expert(self):
            return Still()

    class Still:
        reads = ("goal_x",)

        def label(self, info):
            return np.zeros(2, dtype=np.float32)
""")


def _goal_distance(scene) -> float:
    x, y, _ = scene.robot_pose
    goal = scene.piece("goal")
    return math.hypot(goal.xy[0] - x, goal.xy[1] - y)


def test_the_schedule_rises_on_success_and_never_passes_one():
    schedule = Schedule(start=0.0, threshold=0.8, window=5, step=0.4)
    assert not schedule.add([1, 1, 1, 1])  # the window is not full yet
    assert not schedule.add([0, 0]) and schedule.difficulty == 0.0  # 1,1,1,0,0: 0.6
    assert not schedule.add([1, 1, 1]) and schedule.difficulty == 0.0  # 0,0,1,1,1: 0.6
    assert schedule.add([1]) and schedule.difficulty == 0.4  # 0,1,1,1,1: 0.8 reaches it
    assert schedule.rate() is None  # counted afresh at the new difficulty
    assert not schedule.add([1, 0, 1, 0, 1, 0, 1, 0]) and schedule.difficulty == 0.4
    for _ in range(10):
        schedule.add([1] * 5)
    assert schedule.difficulty == 1.0  # 0.4, 0.8, then 1 (not 1.2), and there it stays
    row: dict = {}
    schedule.after(row, [1] * 5, envs=None)  # at 1 nothing is sent
    assert row[COLUMN] == 1.0


def test_a_resumed_run_continues_at_the_difficulty_of_its_checkpoint():
    options = dagger_args("seek", {"curriculum": True, "curriculum_start": 0.25})
    names = ("iteration", "global_step", COLUMN)
    run = SimpleNamespace(names=names, rows=[(1.0, 10.0, 0.25), (2.0, 20.0, 0.5),
                                             (3.0, 30.0, 0.75)])
    assert Schedule.of(options, run, True, 2).difficulty == 0.5  # the checkpoint's row
    assert Schedule.of(options, run, False, 0).difficulty == 0.25  # a fresh run: the start
    assert Schedule.of(dagger_args("seek", {}), run, True, 2) is None  # no curriculum


def test_seeks_scenes_narrow_below_full_difficulty_and_are_unchanged_at_it():
    full = load_task("seek")
    easy = copy.copy(full)
    easy.difficulty = 0.0
    for seed in range(30):
        scene = easy.scene(np.random.default_rng(seed), True)
        assert _goal_distance(scene) <= 0.5 + 1e-9 and len(scene.pieces) == 1
    assert full.difficulty == 1.0
    assert full.between((0.35, 0.5), full.goal_distance) is full.goal_distance  # exactly
    easy.difficulty = 0.5
    assert easy.between((0.35, 0.5), (0.35, 1.2)) == pytest.approx((0.35, 0.85))
    assert easy.between((0, 0), (1, 2)) == (0, 1)


def test_the_difficulty_reaches_the_env_workers_and_evaluation_stays_at_full():
    """AsyncVectorEnv: the difficulty crosses the pipe to the worker, whose next scene is
    drawn at it; in this process an env lowered to 0 leaves the task every other env (an
    evaluation's) is built from at 1."""
    from jetbot_rt.train.env import JetbotEnv
    from jetbot_rt.train.vec_env import EnvSpec, make_vector_env
    from jetbot_rt.train.wrappers import Shaping

    seed = next(s for s in range(100)  # a seed whose full scene puts the goal far
                if _goal_distance(load_task("seek").scene(np.random.default_rng(s), True)) > 0.8)
    easy = copy.copy(load_task("seek"))
    easy.difficulty = 0.0
    want = easy.scene(np.random.default_rng(seed), True).piece("goal").xy
    envs = make_vector_env(EnvSpec("seek", Config(), Shaping(), 56, keep=("goal_xy",)), 1, None)
    try:
        send(envs, 0.0)
        assert envs.get_attr(COLUMN) == (0.0,)
        _, info = envs.reset(seed=[seed])
        assert tuple(info["goal_xy"][0]) == pytest.approx(want)
    finally:
        envs.close()
    halfway = copy.copy(load_task("seek"))
    halfway.difficulty = 0.5  # a task that says so itself is still built at 1
    training = JetbotEnv(halfway)
    try:
        assert training.difficulty == 1.0 and halfway.difficulty == 0.5
        training.difficulty = 0.0
        assert training.task.difficulty == 0.0 and load_task("seek").difficulty == 1.0
        with pytest.raises(Exception, match=r"difficulty must be a number in \[0, 1\]"):
            training.difficulty = 1.5
    finally:
        training.close()


def test_dagger_raises_a_user_tasks_difficulty_and_writes_it_in_its_metrics(tmp_path, capsys):
    """Iteration 1: the expert drives (nothing counted); 2 and 3: the student, who succeeds
    (a window of one episode): the difficulty each was collected at, 0, 0, 0.5."""
    (tmp_path / "near.py").write_text(CURRICULUM_TASK_SOURCE)
    out = tmp_path / "run"
    result = train_here(capsys, "train", "--task", f"{tmp_path / 'near.py'}:Near", "--algo",
                        "dagger", "--iterations", "3", "--steps-per-iteration", "2", "--beta",
                        "0", "--train-samples", "16", "--batch-size", "16", "--num-envs", "1",
                        "--workers", "0", "--out", str(out), "--no-progress", "--curriculum",
                        "--curriculum-window", "1", "--curriculum-step", "0.5")
    assert result.returncode == 0, result.stderr
    with (out / "metrics.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert [float(row[COLUMN]) for row in rows] == [0.0, 0.0, 0.5]


def test_a_user_task_without_a_curriculum_trains_and_refuses_one(tmp_path, capsys):
    (tmp_path / "mine.py").write_text(TASK_SOURCE)
    task = f"{tmp_path / 'mine.py'}:Mine"
    refused = train_here(capsys, "train", "--task", task, "--algo", "ppo", "--curriculum",
                         "--out", str(tmp_path / "refused"))
    assert refused.returncode == 2
    assert refused.stderr.count("\n") == 1 and "has no curriculum" in refused.stderr
    out = tmp_path / "run"
    result = train_here(capsys, "train", "--task", task, "--algo", "ppo", "--timesteps", "8",
                        "--num-steps", "8", "--num-envs", "1", "--workers", "0",
                        "--update-epochs", "1", "--out", str(out), "--no-progress")
    assert result.returncode == 0, result.stderr
    header = (out / "metrics.csv").read_text().splitlines()[0]
    assert header.startswith("update,global_step") and COLUMN not in header


@pytest.mark.long
def test_ray_workers_get_the_difficulty_and_a_restarted_one_gets_it_again():
    """Ray (about 15 s to start): ``set_attr`` reaches the actor's envs, and an actor Ray
    restarts has it set again before its envs reset with their new seeds."""
    ray = pytest.importorskip("ray")
    from jetbot_rt.train.ray_workers import RESEED_STRIDE
    from jetbot_rt.train.vec_env import EnvSpec, make_vector_env
    from jetbot_rt.train.wrappers import Shaping

    easy = copy.copy(load_task("seek"))
    easy.difficulty = 0.0

    def goals(seeds: list[int]) -> np.ndarray:
        return np.array([easy.scene(np.random.default_rng(s), True).piece("goal").xy
                         for s in seeds])

    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        envs = make_vector_env(EnvSpec("seek", Config(), Shaping(), 56, keep=("goal_xy",)), 2,
                               1, ray="local")
        try:
            send(envs, 0.0)
            _, info = envs.reset(seed=[5, 6])
            assert np.allclose(info["goal_xy"], goals([5, 6]))
            ray.kill(envs.actors[0], no_restart=False)
            _, _, _, _, info = envs.step(np.zeros((2, 2), dtype=np.float32))
            assert envs.restarts == 1
            reseeded = [5 + RESEED_STRIDE, 6 + RESEED_STRIDE]
            assert np.allclose(info["goal_xy"], goals(reseeded))
        finally:
            envs.close()
    finally:
        ray.shutdown()

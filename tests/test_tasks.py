"""The task API: tasks by name (built-in, FILE.py:Class, module:Class, entry point), the
built-ins' seeded scenes unchanged, the scene pieces in the real PyBullet world, and where a
name may come from (a policy's metadata may not name code)."""

from __future__ import annotations

import hashlib
import math
import sys
import textwrap
from pathlib import Path

import gymnasium
import numpy as np
import pytest
from train_runner import train_main

from jetbot_rt.errors import UsageError
from jetbot_rt.tasks import Block, Box, Scene, Tape, Task, Wall, available, load_task
from jetbot_rt.tasks.loader import _LOADED

pytest.importorskip("pybullet")

OLD_SCENES_SHA256 = {
    "forward": "58a2970e15ba8593cff5762d926f4fc9410c64410230275aa2a63115983593c9",
    "seek": "a3446de33bdff013aa30c168b63e20175b3d6f2d7c2f1aec1b13a7fbff79034f",
}
"""sha256 of the scenes the task module before the API drew (``sample_scene`` of forward and
seek, seeds 0..199, start noise on and off, each ``repr((robot_pose, goal_xy, distractors))``
with full float precision): the rewritten tasks must draw the very same numbers."""

TASK_SOURCE = textwrap.dedent("""
    from jetbot_rt.tasks import Block, Scene, Task

    class Mine(Task):
        description = "a planted test task"

        def scene(self, rng, start_noise):
            return Scene((0.0, 0.0, 0.0), (Block((0.5, 0.0), "green", name="goal"),))

        def outcome(self, scene, world):
            return {"is_success": world.distance("goal") < 0.2}
""")


@pytest.fixture(autouse=True)
def _fresh_cache():
    _LOADED.clear()
    yield
    _LOADED.clear()


def _scene_rows(name: str) -> list[str]:
    task = load_task(name)
    rows = []
    for seed in range(200):
        for noise in (True, False):
            scene = task.scene(np.random.default_rng(seed), noise)
            goal, *others = scene.pieces
            rows.append(repr((scene.robot_pose, goal.xy,
                              tuple((b.xy[0], b.xy[1], b.color) for b in others))))
    return rows


@pytest.mark.parametrize("name", ["forward", "seek"])
def test_the_builtins_draw_the_same_scenes_from_a_seed_as_before_the_api(name):
    digest = hashlib.sha256("\n".join(_scene_rows(name)).encode()).hexdigest()
    assert digest == OLD_SCENES_SHA256[name]


def test_a_bad_task_name_is_one_line_exit_2_listing_what_is_available(capsys, tmp_path):
    for command in (["eval", "--task", "nope", "--episodes", "1"],
                    ["train", "--task", "nope", "--out", str(tmp_path / "r")]):
        code, _, err = train_main(capsys, *command)
        assert code == 2
        assert err.count("\n") == 1 and "unknown task 'nope'" in err
        assert "forward, seek" in err and "file.py:Class" in err


def test_help_lists_the_tasks(capsys):
    code, out, _ = train_main(capsys, "--help")
    assert code == 0
    flat = " ".join(out.split())
    assert "forward -- drive to a red block" in flat and "seek -- find the red block" in flat


def test_a_file_task_loads_by_its_path_a_module_never_from_the_working_directory(
        tmp_path, monkeypatch):
    (tmp_path / "planted.py").write_text(TASK_SOURCE)
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend("")  # as `python -m` would put it
    with pytest.raises(UsageError, match="cannot import 'planted'"):
        load_task("planted:Mine")
    assert "planted" not in sys.modules
    task = load_task("planted.py:Mine")
    assert task.short_name() == "mine" and task.description == "a planted test task"
    assert type(load_task("jetbot_rt.tasks.seek:Seek")).__name__ == "Seek"


@pytest.mark.parametrize(("source", "name", "needle"), [
    ("x = 1\n", "t.py:x", "not a subclass of jetbot_rt.tasks.Task"),
    ("x = 1\n", "t.py:Missing", "has no 'Missing'"),
    ("import math\nraise RuntimeError('boom')\n", "t.py:X", "t.py:2: RuntimeError: boom"),
    ("def broken(:\n", "t.py:X", "t.py:1"),
])
def test_a_broken_task_file_is_one_clear_usage_error(tmp_path, source, name, needle):
    (tmp_path / "t.py").write_text(source)
    with pytest.raises(UsageError) as caught:
        load_task(str(tmp_path / name))
    assert needle in str(caught.value) and "\n" not in str(caught.value)


def test_an_installed_packages_task_is_found_by_its_entry_point_name(tmp_path, monkeypatch):
    (tmp_path / "plugin_tasks.py").write_text(TASK_SOURCE)
    info = tmp_path / "plugin_tasks-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: plugin-tasks\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text("[jetbot_rt.tasks]\nmine = plugin_tasks:Mine\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert "mine" in available()
    assert load_task("mine").description == "a planted test task"


def test_the_policys_metadata_may_not_name_code_but_sim_task_may():
    from jetbot_rt.config.sections import from_dict
    from jetbot_rt.hal.registry import BackendOptions
    from jetbot_rt.sim.backend import scene_task

    with pytest.raises(UsageError, match=r"name it yourself: \[sim\] task"):
        scene_task(from_dict({}), BackendOptions((56, 56), task="/tmp/evil.py:X"))
    assert scene_task(from_dict({}), BackendOptions((56, 56), task="seek")) == "seek"
    given = from_dict({"sim": {"task": "my.py:Mine"}})
    assert scene_task(given, BackendOptions((56, 56), task="/tmp/evil.py:X")) == "my.py:Mine"


def test_gymnasium_make_builds_any_task_by_name():
    from jetbot_rt.train.env import JetbotEnv

    env = gymnasium.make("jetbot_rt:Jetbot-v0", task="seek")
    plain = JetbotEnv("seek")
    try:
        first, info = env.reset(seed=5)
        again, _ = plain.reset(seed=5)
        assert env.unwrapped.task.short_name() == "seek" and np.array_equal(first, again)
        assert info["is_success"] is False
    finally:
        env.close()
        plain.close()


class Pieces(Task):
    """Every kind of piece, in front of the robot."""

    def scene(self, rng: np.random.Generator, start_noise: bool) -> Scene:
        track = tuple((0.3 * math.cos(a), 0.3 * math.sin(a))
                      for a in np.linspace(0, 2 * math.pi, 12, endpoint=False))
        return Scene((-0.6, 0.0, 0.0), (
            Tape(track, width=0.05, color="yellow", closed=True, name="track"),
            Box((0.05, 0.6), (0.2, 0.1, 0.1), "blue", yaw=0.3, name="box"),
            Wall((-0.3, -0.3), (-0.3, 0.3), "white", name="wall"),
            Block((0.05, -0.6), "green", name="block"),
        ), floor_color=(0.3, 0.3, 0.3))

    def outcome(self, scene, world):
        return {"is_success": False, "touching": world.touching()}


def test_scene_pieces_are_built_seen_and_touched_in_the_world():
    from jetbot_rt.sim.config import SimConfig
    from jetbot_rt.sim.world import JetbotWorld

    with JetbotWorld(SimConfig(), image_size=(64, 48)) as world:
        world.reset(scene=Pieces().scene(np.random.default_rng(0), False))
        assert world.scene.has("track") and world.shift("box") == 0.0
        assert world.position("wall")[2] == pytest.approx(0.1)
        assert not world.touching()
        world.set_duty(0.0, 0.0)
        world.step(0.2)
        world.reset(robot_pose=(-1.0, 0.0, 0.0), scene=Scene(
            (-0.9, 0.0, 0.0), (Tape(((-0.5, -0.3), (-0.5, 0.3)), 0.1, "yellow"),
                               Wall((-0.3, -0.3), (-0.3, 0.3), "white", name="wall"))))
        image = world.render().astype(int)
        yellow = (image[:, :, 0] > 150) & (image[:, :, 1] > 130) & (image[:, :, 2] < 80)
        assert yellow.sum() > 20  # the tape on the floor, seen by the camera
        assert not world.touching("wall")
        world.set_duty(1.0, 1.0)
        for _ in range(60):
            world.step(1 / 30)
        assert world.touching("wall") and world.touching()
        with pytest.raises(KeyError, match="no piece named 'goal'"):
            world.distance("goal")


def test_a_piece_of_an_unknown_colour_is_a_usage_error():
    from jetbot_rt.sim.config import SimConfig
    from jetbot_rt.sim.world import JetbotWorld

    with JetbotWorld(SimConfig(), image_size=(16, 16)) as world, \
            pytest.raises(UsageError, match="unknown colour 'mauve'"):
        world.reset(scene=Scene((0.0, 0.0, 0.0), (Box((0.5, 0.0), color="mauve"),)))


def test_a_task_file_outside_the_caps_is_refused(tmp_path):
    big = tmp_path / "big.py"
    big.write_text("#" * (1024 * 1024 + 1))
    with pytest.raises(UsageError, match="task file"):
        load_task(f"{big}:X")
    assert Path(big).exists()


@pytest.mark.parametrize(("body", "needle"), [
    ("    def __init__(self, size):\n        pass\n", "Bad() failed: TypeError"),
    ("    episode_steps = 0\n", "episode_steps must be an integer >= 1"),
    ("    max_speed = 2.0\n", "max_speed a number in (0, 1]"),
])
def test_a_task_class_with_bad_settings_is_refused_when_loaded(tmp_path, body, needle):
    (tmp_path / "bad.py").write_text("from jetbot_rt.tasks import Task\n"
                                     f"class Bad(Task):\n{body}")
    with pytest.raises(UsageError, match=r"task '.*bad.py:Bad'") as caught:
        load_task(f"{tmp_path / 'bad.py'}:Bad")
    assert needle in str(caught.value)


def test_an_outcome_without_is_success_is_a_usage_error():
    from jetbot_rt.train.env import JetbotEnv

    class NoVerdict(Pieces):
        def outcome(self, scene, world):
            return {"distance": 1.0}

    env = JetbotEnv(NoVerdict(), image_size=(16, 16))
    try:
        with pytest.raises(UsageError, match="'is_success'"):
            env.reset(seed=0)
    finally:
        env.close()

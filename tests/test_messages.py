"""What a newcomer reads names the real rule and the knob: the evaluation's success rule."""

from __future__ import annotations

from jetbot_rt.tasks import load_task
from jetbot_rt.train.evaluate import success_rule


def test_the_eval_line_states_each_tasks_whole_success_rule() -> None:
    assert success_rule(load_task("forward")) == "final distance < 0.15 m"
    seek = load_task("seek")
    rule = success_rule(seek)
    assert rule is not None and rule.startswith("final distance < 0.15 m and ")
    assert f"the block pushed less than {seek.max_block_shift:g} m" in rule
    assert success_rule(load_task("avoid")) is None, "not a distance task: no such line"

import math

import pytest

from jetbot_rt.errors import Fault
from jetbot_rt.runtime.actions import DEFAULT_MAX_SPEED, ActionPipeline, resolve_max_speed


@pytest.mark.parametrize(
    ("mu", "expected"),
    [
        ((1.0, 1.0), (0.1, 0.1)),
        ((0.5, -0.25), (0.05, -0.025)),
        ((3.0, -7.0), (0.1, -0.1)),  # mu clamped to [-1, 1] before scaling
        ((0.0, 0.0), (0.0, 0.0)),
    ],
)
def test_default_pipeline(mu, expected):
    assert ActionPipeline().duties(mu) == pytest.approx(expected)


def test_trim_and_sign_per_wheel():
    pipeline = ActionPipeline(max_speed=0.5, trim=(0.8, 1.2), sign=(1, -1))
    assert pipeline.duties((1.0, 1.0)) == pytest.approx((0.4, -0.6))


def test_output_clamped_to_unit_range():
    pipeline = ActionPipeline(max_speed=1.0, trim=(2.0, 2.0))
    assert pipeline.duties((1.0, -1.0)) == (1.0, -1.0)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_is_a_fault(bad):
    with pytest.raises(Fault, match="non-finite"):
        ActionPipeline().duties((0.0, bad))


def test_wrong_count_is_a_fault():
    with pytest.raises(Fault, match="expected 2"):
        ActionPipeline().duties((0.0, 0.0, 0.0))


def test_max_speed_resolution_order():
    assert resolve_max_speed(0.3, 0.2) == 0.3
    assert resolve_max_speed(None, 0.2) == 0.2
    assert resolve_max_speed(None, None) == DEFAULT_MAX_SPEED
    assert resolve_max_speed(None, 7.0) == DEFAULT_MAX_SPEED


class TestLimitsOnBothSides:
    """Each wheel's clamps hold in both directions, and only a model's max_speed in (0, 1]
    is taken (mutants of the bounds survived the tests above)."""

    @pytest.mark.parametrize("mu", [(1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0), (1.0, 1.0)])
    def test_each_wheel_clamped_to_unit_range_in_both_directions(self, mu):
        pipeline = ActionPipeline(max_speed=1.0, trim=(2.0, 3.0))
        assert pipeline.duties(mu) == mu

    def test_mu_clamped_before_trim_and_sign(self):
        pipeline = ActionPipeline(max_speed=0.5, trim=(0.5, 1.5), sign=(-1, 1))
        assert pipeline.duties((-4.0, -4.0)) == pytest.approx((0.25, -0.75))

    @pytest.mark.parametrize(("from_model", "expected"),
                             [(1.0, 1.0), (1e-3, 1e-3), (0.0, DEFAULT_MAX_SPEED),
                              (-0.2, DEFAULT_MAX_SPEED), (1.0001, DEFAULT_MAX_SPEED)])
    def test_a_models_max_speed_is_taken_only_in_0_to_1(self, from_model, expected):
        assert resolve_max_speed(None, from_model) == expected


def test_the_pipeline_cannot_be_changed_while_in_use():
    import dataclasses

    pipeline = ActionPipeline()
    with pytest.raises(dataclasses.FrozenInstanceError):
        pipeline.max_speed = 1.0  # type: ignore[misc]


def test_the_config_builder_keeps_each_wheels_trim_and_sign_on_its_own_side():
    from jetbot_rt.config.sections import ActionsConfig

    actions = ActionsConfig(max_speed=0.5, trim=[0.8, 1.2], sign=[-1, 1])
    pipeline = ActionPipeline.from_config(actions)
    assert pipeline.trim == (0.8, 1.2)
    assert pipeline.sign == (-1, 1)
    assert pipeline.duties((1.0, 1.0)) == pytest.approx((-0.4, 0.6))


@pytest.mark.parametrize("mu", [(), (0.5,)])
def test_too_few_action_values_are_a_fault_too(mu):
    with pytest.raises(Fault, match="expected 2"):
        ActionPipeline().duties(mu)


class TestDeadbandLift:
    """``[actions] deadband``: every duty that is not zero is lifted by it, zero stays zero."""

    @pytest.mark.parametrize(("mu", "expected"), [
        ((0.4, -0.4), (0.45, -0.45)),  # 0.2 of duty each way, plus 0.25
        ((0.0, 0.0), (0.0, 0.0)),  # a stop is never lifted
        ((1e-6, -1e-6), (0.25 + 5e-7, -0.25 - 5e-7)),
        ((1.0, -1.0), (0.75, -0.75)),
    ])
    def test_lift_by_sign(self, mu, expected):
        pipeline = ActionPipeline(max_speed=0.5, deadband=0.25)
        assert pipeline.duties(mu) == pytest.approx(expected)

    def test_lifted_duties_stay_in_the_unit_range(self):
        pipeline = ActionPipeline(max_speed=1.0, trim=(1.0, 2.0), deadband=0.5)
        assert pipeline.duties((0.9, -0.9)) == (1.0, -1.0)

    def test_after_trim_and_sign(self):
        pipeline = ActionPipeline(max_speed=0.5, trim=(0.5, 1.0), sign=(-1, 1), deadband=0.1)
        assert pipeline.duties((1.0, 1.0)) == pytest.approx((-0.35, 0.6))

    def test_from_the_config_off_by_default(self):
        from jetbot_rt.config.sections import ActionsConfig

        assert ActionPipeline.from_config(ActionsConfig()).deadband == 0.0
        lifted = ActionPipeline.from_config(ActionsConfig(max_speed=0.5, deadband=0.2))
        assert lifted.duties((0.5, 0.0)) == pytest.approx((0.45, 0.0))

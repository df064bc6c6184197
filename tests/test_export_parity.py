"""The ONNX export refuses a graph that does not compute what the trained network computes.

A network with a Python branch on its input is the classic case: tracing records only the
branch that the export's example input took, so the ONNX file answers differently from the
network for other images. The parity check must catch it, and nothing may be written.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnx")

from jetbot_rt.train.export import (  # noqa: E402
    PARITY_TOLERANCE,
    ExportError,
    export_model,
    parity_error,
)
from jetbot_rt.train.hyperparams import ModelConfig  # noqa: E402
from jetbot_rt.train.model import ActorCritic  # noqa: E402

SMALL = ModelConfig(pool=8, channels=(4, 4, 4), hidden=8)


class BranchOnBrightness(ActorCritic):
    """Adds ``shift`` to mu for bright batches: a data-dependent branch tracing cannot keep."""

    def __init__(self, shift: float) -> None:
        super().__init__(SMALL)
        self.shift = shift

    def forward(self, obs):  # type: ignore[no-untyped-def]
        mu, log_std, value = super().forward(obs)
        if float(obs.float().mean()) > 100.0:  # the export's example (mean ~127) is bright
            mu = mu + self.shift
        return mu, log_std, value


class NaNValue(ActorCritic):
    """Finite weights whose value output is NaN for every image: torch and onnxruntime agree
    that it is NaN, and NaN differs from NaN by NaN."""

    def __init__(self) -> None:
        super().__init__(SMALL)

    def forward(self, obs):  # type: ignore[no-untyped-def]
        mu, log_std, value = super().forward(obs)
        return mu, log_std, value * float("nan")


def export_quietly(model: ActorCritic, out: Path) -> float:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # torch's TracerWarning about the branch
        return export_model(model, out)


class TestExportParity:
    def test_a_graph_that_disagrees_is_refused_and_nothing_is_written(self,
                                                                      tmp_path: Path) -> None:
        out = tmp_path / "policy.onnx"
        with pytest.raises(ExportError, match="parity check failed") as info:
            export_quietly(BranchOnBrightness(shift=1.0), out)
        assert "\n" not in str(info.value)
        assert not out.exists()
        assert list(tmp_path.iterdir()) == []

    def test_a_refused_export_leaves_the_previous_file_alone(self, tmp_path: Path) -> None:
        out = tmp_path / "policy.onnx"
        out.write_bytes(b"the last good export")
        with pytest.raises(ExportError):
            export_quietly(BranchOnBrightness(shift=1.0), out)
        assert out.read_bytes() == b"the last good export"

    def test_a_difference_just_over_the_tolerance_is_refused(self, tmp_path: Path) -> None:
        out = tmp_path / "policy.onnx"
        with pytest.raises(ExportError):
            export_quietly(BranchOnBrightness(shift=2 * PARITY_TOLERANCE), out)
        assert not out.exists()

    def test_a_faithful_graph_is_written_with_its_small_error(self, tmp_path: Path) -> None:
        out = tmp_path / "sub" / "policy.onnx"
        error = export_quietly(BranchOnBrightness(shift=0.0), out)
        assert 0.0 <= error < PARITY_TOLERANCE
        assert out.stat().st_size > 0

    def test_an_output_that_is_nan_on_both_sides_fails_the_parity_check(self,
                                                                       tmp_path: Path) -> None:
        out = tmp_path / "policy.onnx"
        with pytest.raises(ExportError, match=r"parity check failed.* nan"):
            export_quietly(NaNValue(), out)
        assert not out.exists()

    def test_the_parity_error_is_nan_whichever_output_is_nan(self) -> None:
        import io

        model = NaNValue().eval()
        buffer = io.BytesIO()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            torch.onnx.export(model, (torch.zeros(3, 56, 56, 3),), buffer, dynamo=False,
                              input_names=["obs"], output_names=["mu", "log_std", "value"])
        assert math.isnan(parity_error(model, buffer.getvalue()))

    def test_a_network_with_a_non_finite_weight_is_not_exported(self, tmp_path: Path) -> None:
        model = ActorCritic(SMALL)
        with torch.no_grad():
            model.value_head.bias[0] = float("inf")
        with pytest.raises(ExportError, match=r"weight value_head\.bias holds non-finite"):
            export_model(model, tmp_path / "policy.onnx")
        assert list(tmp_path.iterdir()) == []

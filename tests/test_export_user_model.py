"""Bring your own policy: a plain PyTorch network, not ours, exported with ``export_policy``
drives the sim through ``jetbot-rt run``, carries the metadata it was given, and is refused
when its output is NaN. The export snippets of docs/BRING_YOUR_OWN_POLICY.md run verbatim."""

from __future__ import annotations

import math
import re
import warnings
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")
onnx = pytest.importorskip("onnx")

from torch import nn  # noqa: E402

from jetbot_rt.runtime.policy import OnnxPolicy  # noqa: E402
from jetbot_rt.train import export_policy  # noqa: E402
from jetbot_rt.train.export import ExportError  # noqa: E402
from jetbot_rt.train.hyperparams import OptionError  # noqa: E402

DOC = Path(__file__).resolve().parent.parent / "docs" / "BRING_YOUR_OWN_POLICY.md"


class TinyCnn(nn.Module):
    """What a user might write: NCHW frames scaled to 0..1, two convolutions, a tanh head."""

    def __init__(self) -> None:
        super().__init__()
        self.features = nn.Sequential(
            nn.Conv2d(3, 4, kernel_size=3, stride=2), nn.ReLU(),
            nn.Conv2d(4, 8, kernel_size=3, stride=2), nn.ReLU(),
        )
        self.head = nn.Linear(8, 2)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return torch.tanh(self.head(self.features(images).mean(dim=(2, 3))))


class NaNOutput(TinyCnn):
    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return super().forward(images) * float("nan")


def tiny_cnn() -> TinyCnn:
    torch.manual_seed(0)
    return TinyCnn()


def metadata(path: Path) -> dict[str, str]:
    return {prop.key: prop.value for prop in onnx.load(str(path)).metadata_props}


def test_a_plain_pytorch_model_exported_with_export_policy_drives_the_sim(tmp_path: Path) -> None:
    from runner import run_cli

    pytest.importorskip("pybullet")
    path = tmp_path / "mine.onnx"
    error = export_policy(tiny_cnn(), path, image_size=(48, 64), layout="NCHW",
                          pixel_range="0-1", max_speed=0.3)
    assert 0.0 <= error < 1e-4
    result = run_cli(["run", "--backend", "sim", "--policy", str(path), "--duration", "1"],
                     telemetry=tmp_path / "t.jsonl", timeout=120)
    assert result.returncode == 0, result.stderr
    (start,) = result.events("start")
    assert start["policy"]["layout"] == "NCHW"
    assert start["policy"]["size"] == [64, 48]
    assert start["policy"]["pixel_range"] == "0-1"
    assert start["max_speed"] == 0.3
    assert len(result.ticks) >= 10  # 30 at 30 Hz; this only tells ticks from none
    tick = result.ticks[-1]
    assert tick["cmd"] == pytest.approx([0.3 * max(-1.0, min(1.0, m)) for m in tick["mu"]])


def test_the_metadata_is_what_was_asked(tmp_path: Path) -> None:
    path = tmp_path / "mine.onnx"
    export_policy(tiny_cnn(), path, image_size=(32, 40), layout="NCHW", color_order="BGR",
                  pixel_range="-1-1", max_speed=0.25, task="seek", opset=13)
    stated = metadata(path)
    assert {key: stated[key] for key in (
        "jetbot_rt.layout", "jetbot_rt.input_size", "jetbot_rt.color_order",
        "jetbot_rt.pixel_range", "jetbot_rt.max_speed", "jetbot_rt.task")} == {
        "jetbot_rt.layout": "NCHW", "jetbot_rt.input_size": "40x32",
        "jetbot_rt.color_order": "BGR", "jetbot_rt.pixel_range": "-1-1",
        "jetbot_rt.max_speed": "0.25", "jetbot_rt.task": "seek"}
    proto = onnx.load(str(path))
    assert [o.version for o in proto.opset_import if o.domain in ("", "ai.onnx")] == [13]
    assert [i.name for i in proto.graph.input] == ["obs"]
    assert [o.name for o in proto.graph.output] == ["mu"]
    policy = OnnxPolicy.load(path)
    spec = policy.spec
    assert (spec.layout, spec.width, spec.height, spec.color_order, spec.pixel_range) == (
        "NCHW", 40, 32, "BGR", "-1-1")
    assert policy.max_speed == 0.25


def test_max_speed_defaults_to_the_task_s_and_no_task_writes_no_key(tmp_path: Path) -> None:
    export_policy(tiny_cnn(), tmp_path / "seek.onnx", layout="NCHW", task="seek")
    export_policy(tiny_cnn(), tmp_path / "none.onnx", layout="NCHW", task=None)
    assert metadata(tmp_path / "seek.onnx")["jetbot_rt.max_speed"] == "0.5"
    none = metadata(tmp_path / "none.onnx")
    assert none["jetbot_rt.max_speed"] == "0.1"
    assert "jetbot_rt.task" not in none


def test_a_model_with_nan_output_is_refused_and_nothing_is_written(tmp_path: Path) -> None:
    path = tmp_path / "nan.onnx"
    with pytest.raises(ExportError, match=r"parity check failed.* nan.*NaN or infinite") as info:
        export_policy(NaNOutput(), path, layout="NCHW")
    assert "\n" not in str(info.value)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("bad", [
    {"layout": "nhwc"}, {"color_order": "rgb"}, {"pixel_range": "0..255"},
    {"max_speed": 0}, {"max_speed": 1.5}, {"max_speed": math.nan}, {"max_speed": True},
    {"image_size": 0}, {"image_size": (8, 8, 8)}, {"image_size": 16.0}, {"task": "fly"},
    {"opset": 7}, {"opset": 21},
])
def test_an_argument_out_of_range_is_one_line_naming_it(tmp_path: Path, bad: dict) -> None:
    (name,) = bad
    with pytest.raises(OptionError, match=rf"^{name} must be ") as info:
        export_policy(tiny_cnn(), tmp_path / "p.onnx", **{"layout": "NCHW", **bad})
    assert "\n" not in str(info.value)
    assert list(tmp_path.iterdir()) == []


class ThreeActions(TinyCnn):
    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return torch.cat([super().forward(images), images.mean(dim=(1, 2, 3))[:, None]], 1)


class FixedBatch(TinyCnn):
    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return super().forward(images).reshape(2, 2)


@pytest.mark.parametrize(("model", "message"), [
    (ThreeActions(), r"actions have shape \[2, 3\]; the runtime needs \[N, 2\]"),
    (FixedBatch(), r"cannot run the graph on a batch of 3 images"),
])
def test_a_network_the_runtime_cannot_drive_is_refused(tmp_path: Path, model: nn.Module,
                                                      message: str) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # torch's TracerWarning about the fixed shape
        with pytest.raises(ExportError, match=message):
            export_policy(model, tmp_path / "p.onnx", layout="NCHW")
    assert list(tmp_path.iterdir()) == []


def test_the_model_goes_back_in_the_mode_it_came_in(tmp_path: Path) -> None:
    model = nn.Sequential(nn.Flatten(), nn.Dropout(0.5), nn.Linear(8 * 8 * 3, 2)).train()
    error = export_policy(model, tmp_path / "p.onnx", image_size=8)
    assert error < 1e-4  # dropout was off: eval mode while tracing and comparing
    assert model.training


def test_the_doc_s_export_snippets_run_verbatim(tmp_path: Path,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    blocks = re.findall(r"^```python\n(.*?)^```$", DOC.read_text(), flags=re.S | re.M)
    assert len(blocks) == 2, "the doc's export snippet and the raw torch.onnx.export one"
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": "__doc_snippet__"}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # torch's deprecation warning for the raw export
        for block in blocks:
            exec(compile(block, str(DOC), "exec"), namespace)
    for name in ("my_policy.onnx", "raw_policy.onnx"):
        policy = OnnxPolicy.load(tmp_path / name)
        spec = policy.spec
        assert (spec.name, spec.layout, spec.width, spec.height, spec.color_order,
                spec.pixel_range, policy.action_output, policy.max_speed) == (
            "obs", "NHWC", 56, 56, "RGB", "0-255", "mu", 0.1)
    assert metadata(tmp_path / "my_policy.onnx")["jetbot_rt.task"] == "forward"

"""Re-export the first bundled policy (224x224 input, area-pooled by 4 inside the network) at
its network's own 56x56 input, with the same weights and the pooling dropped.

No checkpoint of that run was kept, so the weights come from the ONNX file itself (its
initializers are the trained ``ActorCritic``'s state dict). The new file is written by the
package's exporter, so it has the graph, names and metadata (``jetbot_rt.input_size``
``56x56``) of any policy trained now, and the exporter's own onnxruntime-vs-torch parity check.

Checks before writing, each printed:
- the 224x224 torch network rebuilt from those weights equals the old ONNX file (so the
  weights were read right);
- on 56x56 images, the new model's outputs equal the old model's on the same images
  upsampled by 4 (each pixel repeated 4x4: the old pooling's mean of 16 equal pixels).

    git show 512b1e2:jetbot_rt/policies/forward.onnx > /tmp/forward224.onnx
    python scripts/forward_to_56.py /tmp/forward224.onnx jetbot_rt/policies/forward.onnx
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
import onnx
import onnxruntime as ort
import torch
from onnx import numpy_helper

from jetbot_rt.train.export import export_model
from jetbot_rt.train.hyperparams import LEGACY_IMAGE_SIZE, LEGACY_POOL, ModelConfig
from jetbot_rt.train.model import ActorCritic

TOLERANCE = 1e-4


def weights(proto: onnx.ModelProto) -> dict[str, torch.Tensor]:
    prefix = "model."
    return {init.name[len(prefix):]: torch.from_numpy(numpy_helper.to_array(init).copy())
            for init in proto.graph.initializer if init.name.startswith(prefix)}


def build(state: dict[str, torch.Tensor], size: int, pool: int) -> ActorCritic:
    channels = tuple(int(state[f"encoder.{i}.weight"].shape[0]) for i in (0, 2, 4))
    config = ModelConfig(image_size=size, pool=pool, channels=channels,  # type: ignore[arg-type]
                         hidden=int(state["encoder.7.weight"].shape[0]))
    model = ActorCritic(config)
    model.load_state_dict(state)
    return model.eval()


def run_onnx(proto: onnx.ModelProto, images: np.ndarray) -> list[np.ndarray]:
    session = ort.InferenceSession(proto.SerializeToString(), providers=["CPUExecutionProvider"])
    return session.run(["mu", "log_std", "value"], {"obs": images.astype(np.float32)})


def max_diff(got: list, want: list) -> float:
    pairs = zip(got, want, strict=True)
    return max(float(np.max(np.abs(np.asarray(g) - np.asarray(w)))) for g, w in pairs)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("old", help="the 224x224 forward.onnx")
    parser.add_argument("out", help="where to write the 56x56 model")
    args = parser.parse_args()

    old = onnx.load(args.old)
    meta = {p.key: p.value for p in old.metadata_props}
    state = weights(old)
    small = LEGACY_IMAGE_SIZE // LEGACY_POOL
    rng = np.random.default_rng(0)
    images = rng.integers(0, 256, (8, small, small, 3)).astype(np.float32)
    images[0], images[1] = 0.0, 255.0
    images[2] = images[3] // 64 * 64  # blocky, like a far wall
    upsampled = images.repeat(LEGACY_POOL, axis=1).repeat(LEGACY_POOL, axis=2)

    with torch.no_grad():
        legacy = build(state, LEGACY_IMAGE_SIZE, LEGACY_POOL)
        read_error = max_diff(run_onnx(old, upsampled), [t.numpy() for t in legacy(
            torch.from_numpy(upsampled))])
        model = build(state, small, 1)
    print(f"224x224 torch rebuilt from the ONNX weights vs the old ONNX: max abs diff "
          f"{read_error:.3g}")
    parity = export_model(model, args.out, task=meta.get("jetbot_rt.task", "forward"),
                          max_speed=float(meta.get("jetbot_rt.max_speed", "0.1")))
    print(f"export parity (onnxruntime vs torch, 56x56): {parity:.3g}")
    new_out = run_onnx(onnx.load(args.out), images)
    old_out = run_onnx(old, upsampled)
    mu_error = float(np.max(np.abs(new_out[0] - old_out[0])))
    all_error = max_diff(new_out, old_out)
    print(f"new(56x56 image) vs old(same image upsampled x{LEGACY_POOL}): mu max abs diff "
          f"{mu_error:.3g}, all outputs {all_error:.3g} ({len(images)} images)")
    if not max(read_error, mu_error, all_error) < TOLERANCE:
        print(f"error: difference >= {TOLERANCE}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

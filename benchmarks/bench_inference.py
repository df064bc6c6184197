"""What one inference costs on one CPU thread: the bundled policy and a seed-sized rl_games
network (224x224, 19 M parameters), as the runtime runs them (``OnnxPolicy.infer``: prepare +
onnxruntime, one intra-op thread). Baseline in the same run: numpy's single-threaded float32
matrix multiply, the machine's yardstick for arithmetic throughput.

The Jetson Nano's estimate is on paper: the model's multiply-adds (counted from the graph) at
an effective rate assumed for one Cortex-A57 core (see ``A57_GFLOPS``).

    python benchmarks/bench_inference.py [--runs 1000] [--out benchmarks/results]
        [--policy LABEL FILE.onnx ...]   (more rows: e.g. a candidate beside the bundled one)
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"  # the numpy baseline on one thread too (read at numpy's import)

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import onnx  # noqa: E402
from onnx import numpy_helper, shape_inference  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from policy_models import rl_games_actor_critic  # noqa: E402
from versions import stamp  # noqa: E402

from jetbot_rt.config.sections import PolicyConfig  # noqa: E402
from jetbot_rt.runtime.policy import OnnxPolicy, bundled_policy_path  # noqa: E402

# One A57 core at 1.43 GHz: NEON does 4 float32 FMAs per cycle at best (11.4 GFLOP/s peak);
# onnxruntime's MLAS kernels reach roughly a third of that on small convolutions. An
# assumption, not a measurement: nothing here runs on a Nano.
A57_GFLOPS = (2.0, 4.0)


def multiply_adds(path: Path) -> int:
    """Multiply-adds of the Conv and Gemm/MatMul nodes, from the inferred shapes."""
    model = shape_inference.infer_shapes(onnx.load(path))
    graph = model.graph
    shapes = {}
    for value in [*graph.input, *graph.value_info, *graph.output]:
        dims = value.type.tensor_type.shape.dim
        shapes[value.name] = [d.dim_value for d in dims]
    weights = {t.name: numpy_helper.to_array(t).shape for t in graph.initializer}
    total = 0
    for node in graph.node:
        if node.op_type == "Conv":
            out = shapes[node.output[0]]
            kernel = weights[node.input[1]]  # [out_c, in_c/groups, kh, kw]
            total += int(np.prod(out[1:])) * int(np.prod(kernel[1:]))
        elif node.op_type in ("Gemm", "MatMul") and node.input[1] in weights:
            total += int(np.prod(weights[node.input[1]]))
    return total


def timed_inference(path: Path, runs: int, config: PolicyConfig | None = None) -> dict:
    t0 = time.perf_counter()
    policy = OnnxPolicy.load(path, config, threads=1)
    load_s = time.perf_counter() - t0
    spec = policy.spec
    frame = np.random.default_rng(0).integers(0, 256, (spec.height, spec.width, 3), np.uint8)
    policy.infer(frame)  # first run allocates
    times = []
    for _ in range(runs):
        t = time.perf_counter()
        policy.infer(frame)
        times.append(time.perf_counter() - t)
    ms = np.array(times) * 1e3
    macs = multiply_adds(path)
    median = float(np.median(ms))
    return {
        "model": path.name,
        "input": f"{spec.width}x{spec.height} {spec.layout}",
        "parameters": sum(int(np.prod(numpy_helper.to_array(t).shape))
                          for t in onnx.load(path).graph.initializer),
        "file_mb": round(path.stat().st_size / 2**20, 2),
        "multiply_adds_m": round(macs / 1e6, 1),
        "runs": runs,
        "load_s": round(load_s, 3),
        "median_ms": round(median, 3),
        "p99_ms": round(float(np.percentile(ms, 99)), 3),
        "max_ms": round(float(ms.max()), 3),
        "here_gflops": round(2 * macs / (median * 1e-3) / 1e9, 2),
        "nano_a57_estimate_ms": [round(2 * macs / (g * 1e9) * 1e3, 1) for g in A57_GFLOPS[::-1]],
    }


def numpy_baseline(runs: int = 50, n: int = 256) -> dict:
    """Single-threaded float32 GEMM, GFLOP/s (BLAS threads pinned through the env)."""
    a = np.random.default_rng(1).random((n, n), np.float32)
    b = np.random.default_rng(2).random((n, n), np.float32)
    a @ b
    times = []
    for _ in range(runs):
        t = time.perf_counter()
        a @ b
        times.append(time.perf_counter() - t)
    median = float(np.median(times))
    return {"gemm": f"{n}x{n} float32", "median_ms": round(median * 1e3, 3),
            "gflops": round(2 * n**3 / median / 1e9, 2)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=1000)
    parser.add_argument("--seed-runs", type=int, default=50)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    parser.add_argument("--policy", nargs=2, action="append", default=[],
                        metavar=("LABEL", "FILE"), help="another policy to time, as a row")
    args = parser.parse_args()
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        seed_model = rl_games_actor_critic(Path(tmp) / "rl_games_224.onnx", 224)
        results = {
            "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, "
                       f"{platform.python_version()}",
            "threads": 1,
            "numpy_baseline": numpy_baseline(),
            "bundled": timed_inference(bundled_policy_path(), args.runs),
            "seed_rl_games_224": timed_inference(seed_model, args.seed_runs,
                                                 PolicyConfig(clip=5.0)),
            **{label: timed_inference(Path(path), args.runs) for label, path in args.policy},
            "a57_gflops_assumed": list(A57_GFLOPS),
            "loadavg_before_after": [round(load_before[0], 2), round(os.getloadavg()[0], 2)],
        }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "inference.json").write_text(json.dumps(stamp(results), indent=2) + "\n")
    rows = [
        "| model | input | params | MMAC | load | median | p99 | here GFLOP/s | Nano A57 (est.) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for key in ("bundled", "seed_rl_games_224", *(label for label, _ in args.policy)):
        r = results[key]
        lo, hi = r["nano_a57_estimate_ms"]
        rows.append(
            f"| {key} | {r['input']} | {r['parameters'] / 1e6:.2f} M | {r['multiply_adds_m']} | "
            f"{r['load_s']:.2f} s | {r['median_ms']:.2f} ms | {r['p99_ms']:.2f} ms | "
            f"{r['here_gflops']} | {lo}-{hi} ms |"
        )
    base = results["numpy_baseline"]
    text = "\n".join([
        "# Inference on one CPU thread (`benchmarks/bench_inference.py`)",
        "",
        f"Machine: {results['machine']}; load average before/after "
        f"{results['loadavg_before_after']}.",
        f"Baseline, same run: numpy {base['gemm']} GEMM, {base['gflops']} GFLOP/s.",
        "",
        *rows,
        "",
        f"Nano column: multiply-adds x 2 at {A57_GFLOPS[0]}-{A57_GFLOPS[1]} GFLOP/s for one "
        "Cortex-A57 core (an assumption, not measured).",
        "",
    ])
    (args.out / "inference.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Single-step latency of the exported policy in ONNX Runtime on one CPU core (the torch-free runtime's cost per 50 ms).

For each size, a policy of that preset is exported (``efficienttrack.deploy.export``) and timed two ways, batch 1, one
intra-op thread: the graph alone as the guard calls it (numpy float64 histories → float32 → ONNX Runtime → numpy),
and the whole guarded step (``OnnxRuntime.step``: input checks, histories, graph, rate limit, clamp). Compare with
``benchmarks/policy_latency.py`` (the same policy in torch). Target: p99 ≤ 1 ms.

    python benchmarks/onnx_latency.py [--calls N] [--sizes cpu,paper]
"""

from __future__ import annotations

import argparse
import shlex
import sys
import tempfile
import time
from collections.abc import Callable

import numpy as np
import onnxruntime
import torch

from efficienttrack.deploy.export import export_policy
from efficienttrack.deploy.onnx_runtime import OnnxRuntime, load_onnx_policy
from efficienttrack.learn.policy import AdjustmentPolicy
from efficienttrack.learn.settings import POLICY_PRESETS


def timed(call: Callable[[], object], calls: int, warmup: int = 200) -> tuple[np.ndarray, np.ndarray]:
    """Wall-clock and thread-CPU milliseconds of ``calls`` calls of ``call`` (CPU time excludes preemption)."""
    wall, cpu = np.empty(calls), np.empty(calls)
    for i in range(warmup + calls):
        start, start_cpu = time.perf_counter_ns(), time.thread_time_ns()
        call()
        if i >= warmup:
            wall[i - warmup] = (time.perf_counter_ns() - start) / 1e6
            cpu[i - warmup] = (time.thread_time_ns() - start_cpu) / 1e6
    return wall, cpu


def report(label: str, wall: np.ndarray, cpu: np.ndarray) -> str:
    """One line: wall p50/p99/max, thread CPU p50/p99, and the verdict against 1 ms."""
    p50, p99 = np.percentile(wall, [50, 99])
    c50, c99 = np.percentile(cpu, [50, 99])
    verdict = "ok" if p99 <= 1.0 else "ABOVE 1 ms"
    return (
        f"  {label}: wall p50 {p50:.3f} ms, p99 {p99:.3f} ms [{verdict}], max {wall.max():.3f} ms; "
        f"thread CPU p50 {c50:.3f} ms, p99 {c99:.3f} ms"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=3000, help="timed calls per size and way")
    parser.add_argument("--sizes", default="cpu,paper", help="comma-separated presets: cpu, paper, tiny")
    args = parser.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    print(f"onnxruntime {onnxruntime.__version__}, 1 intra-op thread, batch 1, CPUExecutionProvider")
    rng = np.random.default_rng(0)
    for size in args.sizes.split(","):
        cfg = POLICY_PRESETS[size]
        policy = AdjustmentPolicy(cfg).eval()
        torch.nn.init.normal_(policy.pi_phi.body[-1].weight, std=0.01)
        h, F = cfg.history_length, cfg.future_length
        with tempfile.TemporaryDirectory() as folder:
            export_policy(policy, folder)
            onnx_policy = load_onnx_policy(folder, threads=1)
        obs, q_ref, q_des = rng.normal(size=(1, h, 8)), rng.normal(size=(1, h, 4)), rng.normal(0, 0.01, size=(1, F, 4))
        graph = timed(lambda: onnx_policy(obs, q_ref, q_des), args.calls)  # noqa: B023 (called within the iteration)
        runtime = OnnxRuntime(onnx_policy, limits=None)
        runtime.start(np.zeros((1, 8)))
        step = timed(lambda: runtime.step(np.zeros((1, 8)), q_des), args.calls)  # noqa: B023
        print(f"{size:5s} ({cfg.layers}×{cfg.hidden}, h={h}, F={F}), {args.calls} calls each (wall ≫ CPU: core shared)")
        print(report("graph        ", *graph))
        print(report("guarded step ", *step))
    print("command: python " + " ".join(shlex.quote(a) for a in sys.argv))


if __name__ == "__main__":
    main()

"""Single-step inference latency of the adjustment policy on one CPU core (what the runtime pays every 50 ms).

Times one call as the runtime makes it: numpy histories → float32 tensors → ``policy(o_H, q^r_H, q*_F)`` →
numpy, batch 1, under ``torch.inference_mode``, with ``torch.set_num_threads(1)``. Target: p99 ≤ 1 ms.

    python benchmarks/policy_latency.py [--calls N] [--sizes cpu,paper]
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time

import numpy as np
import torch

from efficienttrack.learn.policy import AdjustmentPolicy
from efficienttrack.learn.settings import POLICY_PRESETS


def latencies(policy: AdjustmentPolicy, calls: int, warmup: int = 200) -> tuple[np.ndarray, np.ndarray]:
    """Wall-clock and thread-CPU milliseconds of ``calls`` single-step calls (CPU time excludes preemption)."""
    h, F = policy.cfg.history_length, policy.cfg.future_length
    rng = np.random.default_rng(0)
    obs, q_ref, q_des = rng.normal(size=(1, h, 8)), rng.normal(size=(1, h, 4)), rng.normal(size=(1, F, 4))
    wall, cpu = np.empty(calls), np.empty(calls)
    with torch.inference_mode():
        for i in range(warmup + calls):
            start, start_cpu = time.perf_counter_ns(), time.thread_time_ns()
            a = policy(*(torch.as_tensor(x, dtype=torch.float32) for x in (obs, q_ref, q_des))).double().numpy()
            if i >= warmup:
                wall[i - warmup] = (time.perf_counter_ns() - start) / 1e6
                cpu[i - warmup] = (time.thread_time_ns() - start_cpu) / 1e6
    assert a.shape == (1, 4)
    return wall, cpu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=3000, help="timed calls per size")
    parser.add_argument("--sizes", default="cpu,paper", help="comma-separated presets: cpu, paper, tiny")
    args = parser.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    print(f"torch {torch.__version__}, 1 thread, batch 1, inference_mode")
    for size in args.sizes.split(","):
        cfg = POLICY_PRESETS[size]
        policy = AdjustmentPolicy(cfg).eval()
        torch.nn.init.normal_(policy.pi_phi.body[-1].weight, std=0.01)
        wall, cpu = latencies(policy, args.calls)
        p50, p99 = np.percentile(wall, [50, 99])
        c50, c99 = np.percentile(cpu, [50, 99])
        verdict = "ok" if p99 <= 1.0 else "ABOVE 1 ms"
        print(
            f"{size:5s} ({cfg.layers}×{cfg.hidden}, h={cfg.history_length}, F={cfg.future_length}): "
            f"wall p50 {p50:.3f} ms, p99 {p99:.3f} ms "
            f"[{verdict}], max {wall.max():.3f} ms; thread CPU time p50 {c50:.3f} ms, p99 {c99:.3f} ms "
            f"({args.calls} calls; wall ≫ CPU means the core was shared)"
        )
    print("command: python " + " ".join(shlex.quote(a) for a in sys.argv))


if __name__ == "__main__":
    main()

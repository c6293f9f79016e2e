"""Loop jitter at 20 Hz: the fixed-rate loop (``efficienttrack.deploy.loop``) in real time against the built-in XE75 simulator.

Runs :class:`~efficienttrack.deploy.loop.Loop` on ``time.monotonic`` along generated loading cycles, one after another, for
``--minutes`` (default 10), in shadow mode, with the policy of ``--policy`` or an untrained one of ``--size``
(the compute per tick is the same). Prints how late the ticks started after their absolute deadlines
(p50/p99/max), the runtime's step time, the overruns and the missed ticks, and the command that produced them.

    python benchmarks/loop_jitter.py [--minutes 10] [--policy policy.pt | --size cpu] [--out DIR]
"""

from __future__ import annotations

import argparse
import shlex
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

from efficienttrack.data.cycles import generate_references
from efficienttrack.deploy.deployment import deploy
from efficienttrack.deploy.loop import MONOTONIC
from efficienttrack.deploy.machine import SimulatedMachine
from efficienttrack.deploy.runtime import Runtime
from efficienttrack.learn.policy import AdjustmentPolicy, load_policy
from efficienttrack.learn.settings import POLICY_PRESETS
from efficienttrack.systems.spec import load_system


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=10.0, help="how long the loop runs")
    parser.add_argument("--policy", type=Path, help="a trained policy.pt (default: an untrained one of --size)")
    parser.add_argument("--size", default="cpu", help="policy preset when no --policy: cpu, paper, tiny")
    parser.add_argument("--out", type=Path, help="folder for the per-tick logs (default: a temporary folder)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    policy = load_policy(args.policy) if args.policy else AdjustmentPolicy(POLICY_PRESETS[args.size]).eval()
    system = load_system("xe75")
    ticks = int(args.minutes * 60 / system.dt)
    refs, total, seed = [], 0, 0
    while total < ticks:
        for ref in generate_references(n=8, seed=seed):
            take = min(len(ref.q), ticks - total + 1)
            if take >= 2:
                refs.append(type(ref)(f"{ref.name}_s{seed}", ref.q[:take]))
                total += take - 1
        seed += 1
    runtime = Runtime(policy, limits=system.limits)
    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or Path(tmp) / "logs"
        results = deploy(refs, runtime, lambda ref: SimulatedMachine(system, ref.q[0], MONOTONIC), system.limits, out,
                         shadow=True)  # fmt: skip
    late = np.concatenate([r.lateness for r in results]) * 1e3
    compute = np.concatenate([r.compute for r in results]) * 1e3
    overruns = sum(r.counts.get("overrun", 0) for r in results)
    missed = sum(r.counts.get("missed_ticks", 0) for r in results)
    p50, p99 = np.percentile(late, [50, 99])
    c50, c99 = np.percentile(compute, [50, 99])
    stopped = [f"{r.name}: {r.reason}" for r in results if r.stopped]
    print(
        f"{len(late)} ticks at 20 Hz ({len(late) * system.dt / 60:.1f} min, {len(results)} references, "
        f"policy {'from ' + str(args.policy) if args.policy else args.size + ' untrained'}, xe75 simulator, shadow mode)"
    )
    print(f"lateness after the deadline: p50 {p50:.3f} ms, p99 {p99:.3f} ms, max {late.max():.3f} ms")
    print(f"runtime step: p50 {c50:.3f} ms, p99 {c99:.3f} ms, max {compute.max():.3f} ms")
    print(f"overruns {overruns}, missed ticks {missed}" + (f"; stopped: {', '.join(stopped)}" if stopped else ""))
    print(f"command: python {shlex.join(sys.argv)}")


if __name__ == "__main__":
    main()

"""Multi-step training throughput of the closed-loop dynamics model: window-steps per second.

One optimizer step rolls ``batch_size`` windows ``h`` steps, so its work is batch × h window-steps.
The figure is measured through the real trainer (:func:`efficienttrack.learn.dynamics.train_model`) on
synthetic records: the time of a run of ``n + k`` steps minus that of a run of ``n`` steps, so the
set-up (windows, scaling) drops out.

    python benchmarks/train_throughput.py [--threads N] [--steps K] [--sizes paper,cpu] [--devices cpu,cuda]
"""

from __future__ import annotations

import argparse
import dataclasses
import shlex
import sys

import numpy as np
import torch

from efficienttrack.data.records import EpisodeRecord
from efficienttrack.learn.dynamics import train_model
from efficienttrack.learn.settings import MAX_STEPS, MODEL_PRESETS


def synthetic_records(episodes: int = 20, steps: int = 500, seed: int = 0) -> list[EpisodeRecord]:
    rng = np.random.default_rng(seed)
    records = []
    for _ in range(episodes):
        q = np.cumsum(rng.normal(0, 0.005, (steps, 4)), 0)
        qd = np.vstack([np.zeros((1, 4)), np.diff(q, axis=0) / 0.05])
        q_des = q + rng.normal(0, 0.01, (steps, 4))
        records.append(EpisodeRecord(q=q, qd=qd, q_ref=q_des, q_des=q_des, u=None, t=np.arange(steps) * 0.05))
    return records


def seconds_per_step(cfg, records, device: str, steps: int) -> float:
    base = dataclasses.replace(cfg, steps=1, epochs=None, save_every=MAX_STEPS)
    train_model(base, records, device=device, progress=False)  # warm-up: one-time allocations and kernel set-up
    short = train_model(base, records, device=device, progress=False).seconds
    long = train_model(dataclasses.replace(base, steps=1 + steps), records, device=device, progress=False).seconds
    return max(long - short, 1e-9) / steps


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's choice)")
    parser.add_argument("--steps", type=int, default=None, help="timed optimizer steps (default 3 paper / 20 cpu)")
    parser.add_argument("--sizes", default="paper,cpu", help="comma-separated presets: paper, cpu, tiny")
    parser.add_argument("--devices", default="cpu,cuda", help="comma-separated; cuda is skipped when not available")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    records = synthetic_records()
    print(f"torch {torch.__version__}, CPU threads {torch.get_num_threads()}, CUDA {torch.cuda.is_available()}")
    for device in args.devices.split(","):
        if device == "cuda" and not torch.cuda.is_available():
            print("cuda: not available, skipped")
            continue
        if device == "cuda":
            print(f"cuda: {torch.cuda.get_device_name()}")
        for size in args.sizes.split(","):
            cfg = MODEL_PRESETS[size]
            steps = args.steps or (3 if size == "paper" and device == "cpu" else 20)
            per_step = seconds_per_step(cfg, records, device, steps)
            rate = cfg.batch_size * cfg.rollout_length / per_step
            print(
                f"{size:5s} ({cfg.layers}×{cfg.hidden}, H={cfg.rollout_length}, batch {cfg.batch_size}) on {device}: "
                f"{rate:,.0f} window-steps/s, {per_step:.3f} s per optimizer step ({steps} steps timed)"
            )
    print("command: python " + " ".join(shlex.quote(a) for a in sys.argv))


if __name__ == "__main__":
    main()

"""Open-loop EfficientTrack at several smoothness weights: its test MAE, smoothness and per-joint error, side by side.

The open-loop policy outputs PWM / 1000, and ``k_smooth`` weighs the change of that command. For each value, one
resumable run of :func:`efficienttrack.baselines.openloop.train_efficienttrack_open` at the ``cpu`` preset with only
``policy.k_smooth`` changed, in OUT/k_<value>, over ``--passes`` collection passes of the training references (the
same seed, so the same collection and plant model for every value).

Run (docs/openloop.md, "How it maps to the paper"):
  .venv/bin/python benchmarks/openloop_smoothness.py --system paper --train-refs ../shared/data/references/train \
      --test-refs ../shared/data/references/test --k 0.01 0.1 1 3 --out runs/openloop_smoothness
"""

from __future__ import annotations

import argparse
import dataclasses
import shlex
import sys
from pathlib import Path

import torch

from efficienttrack.baselines import training_run
from efficienttrack.baselines.openloop import OPEN_PRESETS, train_efficienttrack_open
from efficienttrack.core.progress import ProgressDisplay
from efficienttrack.data.references import load_references
from efficienttrack.systems.spec import SystemSpec


def main() -> None:
    """Train and measure one open-loop run per smoothness weight; print the table."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--system", default="paper", help="built-in system whose plant runs the open loop")
    parser.add_argument("--train-refs", required=True)
    parser.add_argument("--test-refs", required=True)
    parser.add_argument("--k", type=float, nargs="+", required=True, help="the smoothness weights")
    parser.add_argument("--passes", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    print("$ " + " ".join(shlex.quote(a) for a in sys.argv))
    torch.set_num_threads(1)
    train, test = load_references(args.train_refs), load_references(args.test_refs)
    budget = args.passes * sum(ref.steps for ref in train)
    preset = OPEN_PRESETS["cpu"]
    rows = []
    with ProgressDisplay() as bar:
        for k in args.k:
            settings = dataclasses.replace(preset, policy=dataclasses.replace(preset.policy, k_smooth=k))
            run = training_run("open", SystemSpec(system=args.system), train, test, budget, args.seed, args.out / f"k_{k:g}")
            m = train_efficienttrack_open(run, preset=settings, progress=bar)[-1]["metrics"]
            joints = " / ".join(f"{e:.2f}" for e in m["per_joint_mae_deg"])
            rows.append(f"| {k:g} | {m['mae_deg']:.3f} | {m['smt1_deg']:.2f} / {m['smt2_deg']:.2f} | {joints} |")
    print(f"\n{args.passes} pass(es), {budget:,} interaction steps, seed {args.seed}; test MAE on {len(test)} references")
    print("| k_smooth | MAE (°) | 1st / 2nd oSMT (°) | boom / arm / bucket / swing MAE (°) |\n|---:|---:|---|---|")
    print("\n".join(rows))


if __name__ == "__main__":
    main()

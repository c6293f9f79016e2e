"""A baseline's curve with the shared input and with the raw observation: does the input pipeline change what it learns?

Trains one SB3 baseline twice, same seed and settings, once with ``inputs="relative"`` (the standardized relative
features every learner shares) and once with ``inputs="raw"`` (the flat 332 values), on the training references, and
prints the test MAE at each evaluation point side by side, with the wall times. Both start at the PD controller.

Run: .venv/bin/python benchmarks/baseline_inputs.py --system paper --steps 20000 --out runs/bench_inputs
(the paper's split from ../shared/data/references; each run in OUT/<inputs>, resumable)
"""

import argparse
import dataclasses
import shlex
import sys
from pathlib import Path

import torch

from efficienttrack.baselines import method_settings, train_baseline, training_run
from efficienttrack.core.progress import ProgressDisplay
from efficienttrack.data.references import load_references
from efficienttrack.systems.spec import SystemSpec

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "references"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--method", default="sac", choices=["sac", "ppo"])
    parser.add_argument("--preset", default="cpu", help="paper, cpu, sb3 or tiny")
    parser.add_argument("--system", default="paper", help="built-in system the baseline trains on")
    parser.add_argument("--steps", type=int, default=20_000, help="interaction steps of each run")
    parser.add_argument("--points", type=int, nargs="+", default=[1, 2000, 5000, 10000, 15000, 20000])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--refs", type=Path, default=DATA, help="folder with train/ and test/ references")
    parser.add_argument("--out", type=Path, default=Path("runs/bench_inputs"))
    args = parser.parse_args()
    torch.set_num_threads(1)
    train, test = load_references(args.refs / "train"), load_references(args.refs / "test")
    points = [p for p in args.points if p <= args.steps]
    curves = {}
    with ProgressDisplay() as bar:
        for inputs in ("relative", "raw"):
            settings = dataclasses.replace(method_settings(args.method, args.preset), inputs=inputs, device="cpu")
            system = SystemSpec(system=args.system)
            folder = args.out / inputs
            run = training_run("closed", system, train, test, args.steps, args.seed, folder, points)
            curves[inputs] = train_baseline(args.method, run, settings, progress=bar)
    print(f"{args.method} ({args.preset}), closed loop on {args.system}, seed {args.seed}: test MAE °")
    print(f"{'steps':>8} {'relative':>9} {'raw':>9} {'wall s':>7}")
    for rel, raw in zip(curves["relative"], curves["raw"], strict=True):
        mae = (rel["metrics"]["mae_deg"], raw["metrics"]["mae_deg"])
        print(f"{rel['interaction_steps']:>8} {mae[0]:>9.3f} {mae[1]:>9.3f} {rel['wall_seconds']:>7.0f}")
    print("command:", shlex.join([Path(sys.executable).name, *sys.argv]))


if __name__ == "__main__":
    main()

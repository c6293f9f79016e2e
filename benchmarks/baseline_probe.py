"""Probe settings of an SB3 baseline: its curve at each variant of a preset, on the study's split, side by side.

Each ``--variant NAME:FIELD=VALUE,...`` changes fields of the preset (values read as Python literals); the preset itself
runs as ``preset`` unless ``--no-base``. Every run trains ``--loop`` (closed by default) on the training references
less the study's validation references (the same split ``efficienttrack study`` uses) with the same seed, and measures
the test and validation MAE at each evaluation point. Each run is resumable in OUT/<name>.

``--reward research-sac`` trains with the reward the research code's environments carry for SAC, commented out there:
100 (0.2 − RMS_j error), no smoothness term, in place of the environments' one reward (in this process only).

Run (the PPO probe of docs/baselines.md, "PPO's rollout and initial std"):
  .venv/bin/python benchmarks/baseline_probe.py --method ppo --preset sb3 --steps 1000000 --every 100000 \
      --variant 'std0.2:n_steps=256,batch_size=512,gamma=0.98,log_std_init=-1.6' \
      --variant 'std0.5:n_steps=256,batch_size=512,gamma=0.98,log_std_init=-0.7' \
      --variant 'lambda0.99:n_steps=256,batch_size=512,gamma=0.98,log_std_init=-1.6,gae_lambda=0.99' \
      --variant 'lr1e-4:n_steps=256,batch_size=512,gamma=0.98,log_std_init=-1.6,learning_rate=1e-4' \
      --no-base --out runs/probe_ppo
(the paper's split from ../shared/data/references)

The SAC reward probe of docs/comparison.md ("The open loop, with validation"):
  .venv/bin/python benchmarks/baseline_probe.py --method sac --loop open --reward research-sac --steps 100000 \
      --every 25000 --out runs/probe_sac_open_reward
"""

import argparse
import ast
import dataclasses
import shlex
import sys
from pathlib import Path

import numpy as np
import torch

import efficienttrack.envs.core
from efficienttrack.baselines import method_settings, train_baseline, training_run
from efficienttrack.core.progress import ProgressDisplay
from efficienttrack.data.references import load_references
from efficienttrack.study.jobs import default_validation, split_validation
from efficienttrack.systems.spec import SystemSpec

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "references"


def variant(text: str) -> tuple[str, dict[str, object]]:
    """``NAME:FIELD=VALUE,...`` as (name, {field: value}); the values are Python literals."""
    name, _, changes = text.partition(":")
    if not name or not changes:
        raise argparse.ArgumentTypeError(f"--variant {text!r}: expected NAME:FIELD=VALUE[,FIELD=VALUE...]")
    fields = {}
    for change in changes.split(","):
        field, _, value = change.partition("=")
        try:
            fields[field.strip()] = ast.literal_eval(value.strip())
        except (ValueError, SyntaxError) as error:
            raise argparse.ArgumentTypeError(f"--variant {name}: {change!r} is not FIELD=<Python literal>") from error
    return name, fields


def research_sac_reward(error: np.ndarray, change: np.ndarray) -> np.ndarray:
    """The research code's commented-out SAC reward of N machines: ``100 (0.2 − RMS_j(error))``, (N,).

    Args:
        error: (N, 4) rad, the wrapped tracking error.
        change: (N, 4), the change of the action (not used: this reward has no smoothness term).
    """
    return 100.0 * (0.2 - np.sqrt(np.mean(np.square(error), axis=-1)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--method", default="ppo", choices=["sac", "ppo"])
    parser.add_argument("--preset", default="cpu", help="paper, cpu, sb3 or tiny: what the variants change")
    parser.add_argument("--variant", type=variant, action="append", default=[], help="NAME:FIELD=VALUE,...")
    parser.add_argument("--no-base", action="store_true", help="run only the variants, not the preset itself")
    parser.add_argument("--system", default="paper", help="built-in system the baseline trains on")
    parser.add_argument("--loop", default="closed", choices=["closed", "open"])
    parser.add_argument("--reward", default="shared", choices=["shared", "research-sac"], help="see the docstring")
    parser.add_argument("--steps", type=int, default=1_000_000, help="interaction steps of each run")
    parser.add_argument("--every", type=int, default=100_000, help="interaction steps between evaluations")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--refs", type=Path, default=DATA, help="folder with train/ and test/ references")
    parser.add_argument("--out", type=Path, default=Path("runs/probe"))
    args = parser.parse_args()
    base = method_settings(args.method, args.preset)
    runs = ([] if args.no_base else [(args.preset, {})]) + args.variant
    if not runs:
        parser.error("nothing to run: give --variant, or leave out --no-base")
    settings = {}
    for name, fields in runs:
        try:
            settings[name] = dataclasses.replace(base, device="cpu", **fields)
        except TypeError as error:
            parser.error(f"--variant {name}: {error}")
    torch.set_num_threads(1)
    if args.reward == "research-sac":
        efficienttrack.envs.core.reward = research_sac_reward  # what the environments' step calls
    references = load_references(args.refs / "train")
    train, validation = split_validation(references, default_validation(len(references)))
    test = load_references(args.refs / "test")
    points = [1, *range(args.every, args.steps + 1, args.every)]
    system = SystemSpec(system=args.system)
    curves = {}
    with ProgressDisplay() as bar:
        for name, chosen in settings.items():
            run = training_run(args.loop, system, train, test, args.steps, args.seed, args.out / name, points, validation)
            curves[name] = train_baseline(args.method, run, chosen, progress=bar)
    print(f"{args.method} ({args.preset} and variants), {args.loop} loop on {args.system}, {args.reward} reward, "
          f"seed {args.seed}: test MAE ° / validation MAE °, wall s")  # fmt: skip
    for name, fields in runs:
        print(f"  {name}: {fields or '(the preset)'}")
    print(f"{'steps':>9} " + " ".join(f"{name:>20}" for name in settings))
    for row in zip(*curves.values(), strict=True):
        cells = [f"{p['metrics']['mae_deg']:.3f} / {p['validation']['mae_deg']:.3f}, {p['wall_seconds']:.0f}" for p in row]
        print(f"{row[0]['interaction_steps']:>9} " + " ".join(f"{cell:>20}" for cell in cells))
    print("command:", shlex.join([Path(sys.executable).name, *sys.argv]))


if __name__ == "__main__":
    main()

"""SuperTrack with one of its settings changed at a time: which of them makes it learn as fast as it does.

Each ``--variant NAME:FIELD=VALUE,...`` changes fields of the ``cpu`` preset (:class:`SuperTrackSettings`; a dotted
field reaches into its model or policy, e.g. ``model.horizon=20``; values are Python literals); the preset itself runs
as ``preset`` unless ``--no-base``. Every run trains on the training references less the study's validation
references (the split ``efficienttrack study`` uses) with the same seed, and is resumable in OUT/<name>. Printed per
run: the test MAE at its last point at or below each ``--at`` count, at its final point, and at the point its
validation references choose.

Run (docs/comparison.md, "Why SuperTrack learns faster on the XE75"):
  efficienttrack refs generate --n 8 --seed 7 --out runs/study/test_refs
  .venv/bin/python benchmarks/supertrack_ablation.py --system xe75 --train-refs ../shared/data/references/train \
      --test-refs runs/study/test_refs --steps 65536 --at 16384,32768 \
      --variant no-noise:noise_closed=0.0 --variant model-horizon-20:model.horizon=20 --out runs/supertrack_ablation
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

import torch

from baseline_probe import variant
from efficienttrack.baselines import training_run
from efficienttrack.baselines.supertrack import SuperTrackSettings, train_supertrack
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.progress import ProgressDisplay
from efficienttrack.data.references import load_references
from efficienttrack.study.jobs import default_validation, split_validation
from efficienttrack.study.methods import changed_settings
from efficienttrack.study.summary import selected_point
from efficienttrack.systems.spec import SystemSpec


def main() -> None:
    """Run the preset and each variant; print the table."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--variant", type=variant, action="append", default=[], help="NAME:FIELD=VALUE,...")
    parser.add_argument("--no-base", action="store_true", help="run only the variants, not the preset itself")
    parser.add_argument("--system", default="xe75", help="built-in system")
    parser.add_argument("--loop", default="closed", choices=["closed", "open"])
    parser.add_argument("--train-refs", required=True)
    parser.add_argument("--test-refs", required=True)
    parser.add_argument("--steps", type=int, default=65_536, help="interaction steps of each run")
    parser.add_argument("--at", default="", help="comma-separated interaction counts for the table's columns")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    print("$ " + " ".join(shlex.quote(a) for a in sys.argv))
    runs = ([] if args.no_base else [("preset", {})]) + args.variant
    if not runs:
        parser.error("nothing to run: give --variant, or leave out --no-base")
    settings: dict[str, SuperTrackSettings] = {}
    for name, fields in runs:  # the study's --method-set mechanism: every field checked, a dotted one reaching in
        changes = [f"supertrack.{field}={json.dumps(value)}" for field, value in fields.items()]
        try:
            settings[name] = changed_settings("supertrack", "cpu", changes)
        except EfficientTrackError as error:
            parser.error(f"--variant {name}: {error}")
    counts = [int(n) for n in args.at.split(",") if n]
    torch.set_num_threads(1)
    references = load_references(args.train_refs)
    train, validation = split_validation(references, default_validation(len(references)))
    test = load_references(args.test_refs)
    system = SystemSpec(system=args.system)
    rows = []
    with ProgressDisplay() as bar:
        for name, chosen in settings.items():
            run = training_run(args.loop, system, train, test, args.steps, args.seed, args.out / name, None, validation)
            curve = train_supertrack(run, preset=chosen, progress=bar)
            cells = []
            for n in counts:
                early = [p for p in curve if p["interaction_steps"] <= n]
                cells.append(f"{early[-1]['metrics']['mae_deg']:.3f} ({early[-1]['interaction_steps']:,})" if early else "")
            final, best = curve[-1], selected_point(curve)
            cells.append(f"{final['metrics']['mae_deg']:.3f} ({final['interaction_steps']:,})")
            cells.append(f"{best['metrics']['mae_deg']:.3f} ({best['interaction_steps']:,})" if best else "–")
            rows.append(f"| {name} | " + " | ".join(cells) + f" | {final['wall_seconds']:.0f} |")
    print(f"SuperTrack, {args.loop} loop on {args.system}, seed {args.seed}: test MAE ° (interaction steps)")
    for name, fields in runs:
        print(f"  {name}: {fields or '(the cpu preset)'}")
    heads = [f"≤ {n:,}" for n in counts] + ["final", "selected on validation", "training wall (s)"]
    print("| run | " + " | ".join(heads) + " |\n|---|" + "---:|" * len(heads))
    print("\n".join(rows))


if __name__ == "__main__":
    main()

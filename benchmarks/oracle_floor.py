r"""The oracle floor on several systems: the ILC oracle's test MAE trial by trial, one line per system, and its table.

The oracle (:mod:`efficienttrack.baselines.ilc`) runs the test references themselves, with its lead identified from
trial 0 on each system and the same gain everywhere, so nothing is tuned per system. The figure shows whether it has
converged; the CSV holds every point, to re-plot. Run (docs/ilc.md, "The floor on three systems"):

  .venv/bin/python benchmarks/oracle_floor.py --out docs/figures/oracle-floor \
      --system "paper=paper|../shared/data/references/test" \
      --system "paper, delay 1, lag 0.1 s, dead band 10=paper:delay=1,lag=0.1,dead_band=10|../shared/data/references/test" \
      --system "xe75=xe75|runs/study/test_refs"

Each ``--system`` is ``LABEL=SPEC[:key=value,...]|TEST_REFS[|POLICY]``; with a policy checkpoint the oracle learns its
corrections on top of that policy's adjustments (trial 0: the policy alone). Writes ``OUT.png`` and ``OUT.csv`` (label, trial,
interaction_steps, mae_deg) and prints a Markdown table with the identified leads. ``--trials`` and ``--cutoff`` run
the oracle with more trials or another low-pass than its ``cpu`` preset (80 trials, 1.5 Hz), the same on every system.
"""

from __future__ import annotations

import argparse
import csv
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import json

import matplotlib.pyplot as plt
from matplotlib import ticker

from efficienttrack.baselines.curve import CURVE_FILE, training_run
from efficienttrack.baselines.ilc import ILC_PRESETS, train_ilc, trial_steps
from efficienttrack.cli.common import parse_options
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.progress import ProgressDisplay
from efficienttrack.data.references import load_references
from efficienttrack.systems.spec import SystemSpec


def parse_system(text: str) -> tuple[str, SystemSpec, Path, Path | None]:
    """``LABEL=SPEC[:key=value,...]|TEST_REFS[|POLICY]`` as (label, spec, test references folder, policy or None)."""
    label, _, rest = text.partition("=")
    spec, _, rest = rest.partition("|")
    refs, _, policy = rest.partition("|")
    name, _, options = spec.partition(":")
    if not (label and name and refs):
        sys.exit(f"--system '{text}': expected LABEL=SPEC[:key=value,...]|TEST_REFS[|POLICY]")
    opts = parse_options(options.split(",") if options else None, "--system")
    return label, SystemSpec(system=name, options=tuple(opts.items())), Path(refs), Path(policy) if policy else None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--system", action="append", required=True, help="LABEL=SPEC[:key=value,...]|TEST_REFS[|POLICY]")
    parser.add_argument("--out", type=Path, required=True, help="OUT.png and OUT.csv are written")
    parser.add_argument("--trials", type=int, default=ILC_PRESETS["cpu"].trials, help="learning trials after trial 0")
    parser.add_argument("--cutoff", type=float, default=ILC_PRESETS["cpu"].cutoff_hz, help="the low-pass Q's cut-off, Hz")
    args = parser.parse_args()
    if args.trials < 40:
        sys.exit(f"--trials {args.trials}: the table reads trials 10 and 40 and the last 16; give at least 40")
    # every input read before the first system runs, so that a bad one stops it at once rather than minutes later
    settings = replace(ILC_PRESETS["cpu"], trials=args.trials, cutoff_hz=args.cutoff)
    systems = [parse_system(text) for text in args.system]
    loaded = [(label, spec, load_references(refs_dir), policy) for label, spec, refs_dir, policy in systems]
    for label, _, _, policy in loaded:
        if policy is not None and not policy.is_file():
            sys.exit(f"--system '{label}': policy {policy}: no such file")
    trials = settings.trials
    rows, figure = [], plt.figure(figsize=(7, 4))
    for label, spec, refs, policy in loaded:
        with tempfile.TemporaryDirectory() as folder:
            run = training_run("closed", spec, refs, refs, (trials + 1) * trial_steps(refs), 0, folder)
            curve = train_ilc(run, preset=settings, progress=ProgressDisplay(label), policy=policy)
            lead = json.loads((Path(folder) / CURVE_FILE).read_text())["lead_identified"]
        mae = [point["metrics"]["mae_deg"] for point in curve]
        rows += [(label, k, point["interaction_steps"], m) for k, (point, m) in enumerate(zip(curve, mae, strict=True))]
        plt.semilogy(range(len(mae)), mae, label=f"{label} (lead {lead}{', on its policy' if policy else ''})")
        last = mae[-17:]
        print(f"| {label} | {lead} | {mae[0]:.3f} | {mae[10]:.3f} | {mae[40]:.3f} | {mae[-1]:.3f} ({trials}) | "
              f"{100 * (last[0] - last[-1]) / last[0]:.1f} % |", flush=True)  # fmt: skip
    plt.xlabel("trial (trial 0: the PD controller alone, or the policy where a line runs on one)")
    plt.ylabel("test MAE (°)")
    plt.title(f"ILC oracle floor: lead identified per system, gain 0.35, low-pass {settings.cutoff_hz:g} Hz")
    plt.gca().yaxis.set_major_locator(ticker.FixedLocator([0.1, 0.2, 0.3, 0.5, 1, 2, 3, 5]))
    plt.gca().yaxis.set_major_formatter(ticker.FormatStrFormatter("%g"))
    plt.gca().yaxis.set_minor_formatter(ticker.NullFormatter())
    plt.grid(True, which="both", alpha=0.3)
    plt.legend()
    plt.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(args.out.with_suffix(".png"), dpi=120)
    with open(args.out.with_suffix(".csv"), "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["system", "trial", "interaction_steps", "mae_deg"])
        writer.writerows((label, k, steps, f"{m:.6f}") for label, k, steps, m in rows)


if __name__ == "__main__":
    try:
        main()
    except EfficientTrackError as error:  # bad settings, references, policy or system: the message, not a traceback
        sys.exit(f"oracle_floor: {error}")

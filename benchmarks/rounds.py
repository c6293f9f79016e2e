"""Rounds benchmark: `efficienttrack run --rounds 3` on the built-in xe75 over seeds, for the full and the fastset budget.

For each preset (``cpu``: ten collection passes, then rounds; ``fastset``: one pass, then rounds) and seed, a full
resumable run under OUT/<preset>/seed_<s> (the demo's references: 32 training, 8 test cycles). Prints, per round,
mean ± std over seeds of the test MAE, its ratio to PD, the 1st/2nd-order smoothness, Tr/Te.MPE, the interaction
steps (I.S.) and the training time, then each run's wall time, and writes the same as OUT/rounds_benchmark.json.
With ``--time-budget MINUTES`` every run is given its minutes (``RunConfig.time_budget``), and each wall time is
checked against them: the issue's target is three fastset rounds within 15 minutes on 2 cores.

    .venv/bin/python benchmarks/rounds.py --presets cpu fastset --seeds 0 1 2 --out runs/bench_rounds
    .venv/bin/python benchmarks/rounds.py --presets fastset --time-budget 15 --threads 2 --out runs/bench_budget
    .venv/bin/python benchmarks/rounds.py --presets fastset --set policy.imagined_share=0.5 --out runs/bench_im
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from rich.console import Console
from rich.table import Table

from efficienttrack.core.fileio import write_json
from efficienttrack.core.settings import merge, parse_override
from efficienttrack.data.cycles import generate_references
from efficienttrack.systems.spec import SystemSpec
from efficienttrack.workflow.config import PRESETS, RunConfig, amend
from efficienttrack.workflow.pipeline import DEMO_REFERENCES, DEMO_SEED, DEMO_TRAIN, run_pipeline

COLUMNS = (
    ("MAE °", "{:.3f}", lambda r, pd: r["efficienttrack"]["mae_deg"]),
    ("MAE / PD", "{:.3f}", lambda r, pd: r["efficienttrack"]["mae_deg"] / pd["mae_deg"]),
    ("1st oSMT °", "{:.3f}", lambda r, pd: r["efficienttrack"]["smt1_deg"]),
    ("2nd oSMT °", "{:.3f}", lambda r, pd: r["efficienttrack"]["smt2_deg"]),
    ("Tr.MPE °", "{:.3f}", lambda r, pd: r["model"]["tr_mpe_deg"]),
    ("Te.MPE °", "{:.3f}", lambda r, pd: r["model"]["te_mpe_deg"]),
    ("I.S.", "{:.0f}", lambda r, pd: r["interaction_steps"]),
    ("train s", "{:.0f}", lambda r, pd: r["train_seconds"]),
)
"""Columns of a round: heading, format, and how to read it from a round's entry of metrics.json and PD's metrics."""
PD_COLUMNS = {"MAE °": "mae_deg", "1st oSMT °": "smt1_deg", "2nd oSMT °": "smt2_deg"}
"""Columns the PD row has: heading → key of the PD metrics."""


def _mean_std(values: list[float]) -> list[float]:
    return [float(np.mean(values)), float(np.std(values))]


def summarize(runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per round: mean and std over the runs of every column, plus PD's MAE and smoothness.

    Args:
        runs: the runs' metrics.json contents (with ``rounds``), one per seed.

    Returns:
        One entry per round (and one for PD first): ``{"method", column heading: [mean, std], ...}``.
    """
    rows = [{"method": "PD", **{heading: _mean_std([m["pd"][key] for m in runs]) for heading, key in PD_COLUMNS.items()}}]
    for k in range(min(len(m["rounds"]) for m in runs)):
        row = {heading: _mean_std([read(m["rounds"][k], m["pd"]) for m in runs]) for heading, _, read in COLUMNS}
        rows.append({"method": f"Round {k + 1}", **row})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=["cpu", "fastset"], choices=list(PRESETS), help="run settings")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="seeds of collection noise and training")
    parser.add_argument("--rounds", type=int, default=3, help="rounds per run")
    parser.add_argument("--out", type=Path, default=Path("runs/bench_rounds"), help="output folder")
    parser.add_argument("--device", default="auto", help="auto, cpu or cuda")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    parser.add_argument("--time-budget", type=float, default=None, help="minutes per run (default: no budget)")
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="SECTION.FIELD=VALUE",
        help="change one setting of every run, as the command line's --set (repeatable)",
    )
    args = parser.parse_args()
    changes: dict[str, Any] = {}
    for text in args.set:
        changes = merge(changes, parse_override(text))
    if args.threads:
        torch.set_num_threads(args.threads)
    refs = generate_references(DEMO_REFERENCES, seed=DEMO_SEED)
    train, test = refs[:DEMO_TRAIN], refs[DEMO_TRAIN:]
    console = Console(width=160)
    report: dict[str, Any] = {"command": shlex.join([sys.executable, *sys.argv]), "presets": {}}
    for name in args.presets:
        base: RunConfig = PRESETS[name]
        runs, walls = [], []
        for seed in args.seeds:
            options = {"seed": seed, "device": args.device, "rounds": args.rounds, "time_budget": args.time_budget}
            given = {name: value for name, value in options.items() if value is not None}
            cfg = amend(base, merge(changes, given), "benchmarks/rounds.py")
            start = time.perf_counter()
            runs.append(run_pipeline(SystemSpec(), train, test, args.out / name / f"seed_{seed}", cfg, console).metrics)
            walls.append(time.perf_counter() - start)
        rows = summarize(runs)
        report["presets"][name] = {"seeds": args.seeds, "rounds": rows, "wall_seconds": walls}
        if args.time_budget is not None:
            within = [w <= 60 * args.time_budget for w in walls]
            report["presets"][name]["within_time_budget"] = within
        table = Table(title=f"xe75, {len(train)} train / {len(test)} test references, preset {name}, seeds {args.seeds}")
        table.add_column("method")
        for heading, _, _ in COLUMNS:
            table.add_column(heading, justify="right")
        for row in rows:
            cells = [f"{fmt.format(row[h][0])} ± {fmt.format(row[h][1])}" if h in row else "–" for h, fmt, _ in COLUMNS]
            table.add_row(row["method"], *cells)
        console.print(table)
        console.print(f"wall time per run (s, resumed stages not counted): {', '.join(f'{w:.0f}' for w in walls)}")
        if args.time_budget is not None:
            console.print(f"within the time budget of {args.time_budget:g} min: {sum(within)} of {len(walls)} runs")
    write_json(args.out / "rounds_benchmark.json", report)
    console.print("command: " + report["command"])


if __name__ == "__main__":
    main()

"""Tracking benchmark: `efficienttrack run` on the built-in xe75 over several seeds, PD alone vs EfficientTrack.

Prints mean ± std over seeds of every tracking metric, the interaction steps (I.S.), training and wall
time, and the command that produced the figures. Each seed is a full resumable run under OUT/seed_<s>,
so an interrupted benchmark picks up where it stopped.

    .venv/bin/python benchmarks/tracking.py --preset cpu --seeds 0 1 2 --out runs/bench_tracking
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from rich.console import Console
from rich.table import Table

from efficienttrack.data.cycles import generate_references
from efficienttrack.systems.spec import SystemSpec
from efficienttrack.workflow.config import PRESETS, RunConfig
from efficienttrack.workflow.pipeline import DEMO_REFERENCES, DEMO_SEED, DEMO_TRAIN, run_pipeline

ROWS = (
    ("MAE (°)", "mae_deg"),
    ("RMSE (°)", "rmse_deg"),
    ("FMAE (°)", "fmae_deg"),
    ("1st oSMT (°)", "smt1_deg"),
    ("2nd oSMT (°)", "smt2_deg"),
    ("ETD-MAE (cm)", "etd_mae_cm"),
    ("ETD-FMAE (cm)", "etd_fmae_cm"),
)


def _cell(values: list[float]) -> str:
    return f"{np.mean(values):.3f} ± {np.std(values):.3f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="cpu", choices=list(PRESETS), help="run settings (cpu = the demo's)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="seeds of collection noise and training")
    parser.add_argument("--out", type=Path, default=Path("runs/bench_tracking"), help="output folder (one run per seed)")
    parser.add_argument("--device", default="auto", help="auto, cpu or cuda")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    base: RunConfig = PRESETS[args.preset]
    refs = generate_references(DEMO_REFERENCES, seed=DEMO_SEED)
    train, test = refs[:DEMO_TRAIN], refs[DEMO_TRAIN:]
    console = Console(width=160)
    results, walls = [], []
    for seed in args.seeds:
        cfg = replace(base, seed=seed, device=args.device, collect=replace(base.collect, seed=seed))
        start = time.perf_counter()
        results.append(run_pipeline(SystemSpec(), train, test, args.out / f"seed_{seed}", cfg, console).metrics)
        walls.append(time.perf_counter() - start)

    table = Table(title=f"xe75, {len(train)} train / {len(test)} test references, preset {args.preset}, seeds {args.seeds}")
    table.add_column("metric")
    table.add_column("PD")
    table.add_column("EfficientTrack")
    for label, key in ROWS:
        table.add_row(label, _cell([m["pd"][key] for m in results]), _cell([m["efficienttrack"][key] for m in results]))
    ratio = [m["efficienttrack"]["mae_deg"] / m["pd"]["mae_deg"] for m in results]
    table.add_row("MAE ratio ET/PD", "", _cell(ratio))
    table.add_row("Tr.MPE / Te.MPE (°)", "", f"{_cell([m['model']['tr_mpe_deg'] for m in results])} / "
                  f"{_cell([m['model']['te_mpe_deg'] for m in results])}")  # fmt: skip
    table.add_row("I.S.", "", _cell([m["interaction_steps"] for m in results]))
    table.add_row("train time (s)", "", _cell([m["train_seconds"] for m in results]))
    table.add_row("wall time per seed (s)", "", _cell(walls))
    console.print(table)
    console.print("command: " + shlex.join([sys.executable, *sys.argv]))


if __name__ == "__main__":
    main()

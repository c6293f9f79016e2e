"""Where the tracking error of a run lies: per joint, moving vs held reference, for PD and every round's policy.

Reads the test episodes of a finished run folder (``records/pd``, ``records/efficienttrack`` and
``rounds/<k>/records/efficienttrack``) and prints, per joint, the share of steps whose reference holds still,
the MAE while the reference moves and while it holds, and the signed mean error while it holds (an offset).

    .venv/bin/python benchmarks/precision.py runs/demo
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from rich.console import Console
from rich.table import Table

from efficienttrack.core.joints import JOINT_NAMES
from efficienttrack.data.metrics import HELD_SPEED_DEG_S, moving_held_split
from efficienttrack.data.records import load_records


def run_episodes(out: Path) -> dict[str, Path]:
    """The test-episode folders of a run: PD, round 1 and every later round, in order."""
    folders = {"PD": out / "records" / "pd", "Round 1": out / "records" / "efficienttrack"}
    later = sorted((p for p in (out / "rounds").glob("*") if p.name.isdigit()), key=lambda p: int(p.name))
    folders |= {f"Round {p.name}": p / "records" / "efficienttrack" for p in later}
    return {name: folder for name, folder in folders.items() if folder.is_dir()}


def _cell(value: float | None) -> str:
    return "–" if value is None else f"{value:.2f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a finished run folder (efficienttrack run / demo --out)")
    parser.add_argument("--held-speed", type=float, default=HELD_SPEED_DEG_S, help="held below this desired speed, °/s")
    parser.add_argument("--json", action="store_true", help="print one JSON object per method instead of the table")
    args = parser.parse_args()
    folders = run_episodes(args.run)
    if not folders:
        parser.error(f"{args.run}: no records/pd or records/efficienttrack folder (is it a finished run?)")
    splits = {name: moving_held_split(load_records(folder), args.held_speed) for name, folder in folders.items()}
    if args.json:
        for name, split in splits.items():
            print(json.dumps({"method": name, **split}))
        return
    table = Table(title=f"tracking error by joint, moving vs held reference (< {args.held_speed:g} °/s): {args.run}")
    for heading in ("method", "joint", "held share", "MAE moving °", "MAE held °", "bias held °"):
        table.add_column(heading, justify="left" if heading in ("method", "joint") else "right")
    for name, split in splits.items():
        for j, joint in enumerate(JOINT_NAMES):
            cells = (split["moving_mae_deg"][j], split["held_mae_deg"][j], split["held_bias_deg"][j])
            table.add_row(name if j == 0 else "", joint, f"{split['held_share'][j]:.2f}", *map(_cell, cells))
        table.add_section()
    Console(width=120).print(table)


if __name__ == "__main__":
    main()

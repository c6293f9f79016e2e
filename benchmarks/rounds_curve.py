"""EfficientTrack's rounds against a study's curves: MAE against interaction steps, one figure and one table.

Each RUN is a run folder with rounds (``efficienttrack run --rounds K``, one seed each); a round's point is its
interaction steps (I.S.) and its policy's MAE on the run's test references (``metrics.json``'s ``rounds``), or, with
``--scored DIR``, on the references of the evaluation ``RUN/DIR/round_<k>/metrics.json`` (``efficienttrack evaluate``
of ``RUN/rounds/<k>/policy.pt``). Runs of one group (``--group NAME=RUN,RUN,...``) are seeds of one line: mean ± sample
std over them where every seed has the round. A committed study file (``--study FILE``, a study's ``results.json``)
adds each method's mean curve over its seeds (± sample std), on its validation references (``--study-metric
validation``) or its test references (``test``); ``--floor`` draws the ILC oracle's floor (docs/ilc.md).
``--export FILE`` keeps the groups' points (small JSON, for committing); ``--from FILE`` redraws
from such a file without the run folders.

    python benchmarks/rounds_curve.py --group paper=runs/r40/paper_fs4_s0,runs/r40/paper_fs4_s1 --out rounds.png
    python benchmarks/rounds_curve.py --group xe75=runs/r40/xe75_fs4_s0 --study docs/results/table1-xe75-closed.json \
        --study-metric validation --export docs/results/rounds-xe75-validation.json --out xe75.png
    python benchmarks/rounds_curve.py --from docs/results/rounds-xe75-validation.json --out xe75.png
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.ticker import FormatStrFormatter  # noqa: E402

from efficienttrack.core.errors import EfficientTrackError  # noqa: E402
from efficienttrack.core.fileio import write_json  # noqa: E402
from efficienttrack.study.methods import METHODS  # noqa: E402
from efficienttrack.study.summary import mean_curve  # noqa: E402


def round_points(run: Path, scored: str | None) -> list[dict[str, Any]]:
    """A run's rounds as points ``{"interaction_steps", "mae_deg"}``, in order.

    Args:
        run: the run folder (its ``metrics.json`` has ``rounds``).
        scored: a folder under ``run`` with ``round_<k>/metrics.json`` for each round, or None for the run's own test
            references.

    Returns:
        One point per round that has its figures (a round not yet scored in ``scored`` is left out).
    """
    path = run / "metrics.json"
    if not path.is_file():
        raise EfficientTrackError(f"{path}: no metrics.json (the run has not finished)")
    points = []
    for entry in json.loads(path.read_text())["rounds"]:
        if scored is None:
            points.append({"interaction_steps": entry["interaction_steps"], "mae_deg": entry["efficienttrack"]["mae_deg"]})
            continue
        metrics = run / scored / f"round_{entry['round']}" / "metrics.json"
        if metrics.is_file():
            mae = json.loads(metrics.read_text())["efficienttrack"]["mae_deg"]
            points.append({"interaction_steps": entry["interaction_steps"], "mae_deg": mae})
    return points


def study_curves(path: Path, metric: str) -> dict[str, list[dict[str, Any]]]:
    """Each method's mean curve over its seeds in a study's ``results.json``, by method name.

    Args:
        path: the file.
        metric: ``validation`` (the points' validation MAE) or ``test``.
    """
    jobs = json.loads(path.read_text())["jobs"]
    by_method: dict[str, list[list[dict[str, Any]]]] = {}
    for job in jobs:
        points = [
            {"interaction_steps": p["interaction_steps"],
             "mae_deg": p["validation"]["mae_deg"] if metric == "validation" else p["metrics"]["mae_deg"]}
            for p in job["curve"] if metric == "test" or "validation" in p
        ]  # fmt: skip
        if points:
            by_method.setdefault(job["method"], []).append(points)
    return {method: mean_curve(curves) for method, curves in by_method.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--group", action="append", default=[], help="NAME=RUN[,RUN...]: the seeds of one line")
    parser.add_argument("--from", dest="source", type=Path, default=None, help="the groups' points from an --export file")
    parser.add_argument("--export", type=Path, default=None, help="write the groups' points here (JSON)")
    parser.add_argument("--scored", default=None, help="evaluations under each run: DIR/round_<k>/metrics.json")
    parser.add_argument("--study", type=Path, default=None, help="a study's results.json whose curves to draw beside")
    parser.add_argument("--study-metric", choices=("validation", "test"), default="test")
    parser.add_argument("--floor", action="append", default=[], help="[PLANT=]MAE: the ILC oracle's floor (°), a line")
    parser.add_argument("--title", default="MAE against interaction steps")
    parser.add_argument("--out", type=Path, required=True, help="the figure (.png)")
    args = parser.parse_args()
    floors = []
    for floor in args.floor:
        plant, _, value = floor.rpartition("=")
        try:
            floors.append((plant, float(value)))
        except ValueError:
            parser.error(f"--floor '{floor}': expected [PLANT=]MAE, e.g. xe75=0.337")
    if bool(args.group) == (args.source is not None):
        parser.error("give --group (run folders) or --from (an --export file), not both")
    if args.source is not None:
        try:
            groups = json.loads(args.source.read_text())["groups"]
        except (OSError, ValueError, KeyError) as exc:
            parser.error(f"--from {args.source}: not an --export file of this script ({type(exc).__name__}: {exc})")
    else:
        groups = {}
        for group in args.group:
            name, sep, runs = group.partition("=")
            if not sep or not name or not runs:
                parser.error(f"--group '{group}': expected NAME=RUN[,RUN...]")
            try:
                groups[name] = [{"run": run, "points": round_points(Path(run), args.scored)} for run in runs.split(",")]
            except (EfficientTrackError, OSError, ValueError, KeyError) as exc:
                parser.error(f"--group '{name}': {exc}")
    if args.export is not None:
        command = f"python benchmarks/rounds_curve.py {shlex.join(sys.argv[1:])}"
        write_json(args.export, {"groups": groups, "scored": args.scored, "command": command})

    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    print(f"| line | seeds | {' | '.join(['I.S. → MAE (°)'])} |\n|---|---:|---|")
    for name, seeds in groups.items():
        curves = [seed["points"] for seed in seeds]
        rows = mean_curve([c[: min(len(c) for c in curves)] for c in curves])
        steps = np.array([r["interaction_steps"] for r in rows])
        mae = np.array([r["mae_deg"] for r in rows])
        std = np.array([r["mae_deg_std"] or 0.0 for r in rows])
        ax.plot(steps, mae, "o-", label=f"{name} ({len(curves)} seed{'s' * (len(curves) > 1)})")
        ax.fill_between(steps, mae - std, mae + std, alpha=0.2)
        cells = ", ".join(
            f"{s:,} → {m:.3f}" + (f" ± {d:.3f}" if len(curves) > 1 else "") for s, m, d in zip(steps, mae, std, strict=True)
        )
        print(f"| {name} | {len(curves)} | {cells} |")
    if args.study is not None:
        for method, rows in study_curves(args.study, args.study_metric).items():
            if method == "pd":
                ax.axhline(rows[0]["mae_deg"], color="k", ls=":", lw=1, label=f"PD (study, {args.study_metric})")
                continue
            steps = np.array([max(r["interaction_steps"], 1) for r in rows])
            mae = np.array([r["mae_deg"] for r in rows])
            std = np.array([r["mae_deg_std"] or 0.0 for r in rows])
            name = "EfficientTrack, one round of 1–10 passes" if method == "efficienttrack" else METHODS[method].label
            [line] = ax.plot(steps, mae, "s--" if method == "efficienttrack" else "-", alpha=0.8,
                             label=f"{name} (study, {args.study_metric}, {rows[-1]['seeds']} seeds)")  # fmt: skip
            ax.fill_between(steps, mae - std, mae + std, color=line.get_color(), alpha=0.15)
            cells = ", ".join(f"{r['interaction_steps']:,} → {r['mae_deg']:.3f}" for r in rows if r["interaction_steps"] > 0)
            print(f"| {name} (study) | {rows[-1]['seeds']} | {cells} |")
    for i, (plant, mae) in enumerate(floors):
        label = f"floor{f' ({plant})' if plant else ''}: the ILC oracle on the test references ({mae:.3f}°)"
        ax.axhline(mae, color="k", ls=("-.", (0, (1, 3)))[i % 2], lw=1, label=label)
    ax.set_xscale("log")
    ax.set_yscale("log")  # PD's line and the learners' tenths of a degree on one axis
    for axis in (ax.yaxis.set_major_formatter, ax.yaxis.set_minor_formatter):
        axis(FormatStrFormatter("%.2g"))
    ax.set_xlabel("training interaction steps")
    ax.set_ylabel("MAE (°)")
    ax.set_title(args.title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=120)
    print(f"\nfigure: {args.out}\ncommand: python benchmarks/rounds_curve.py {shlex.join(sys.argv[1:])}")


if __name__ == "__main__":
    main()

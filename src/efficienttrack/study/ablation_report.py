"""An ablation's report, rebuilt from its jobs' folders every time: table (Markdown, CSV), ``ablation.json``, figure.

One row per variant: the mean and the sample standard deviation over the seeds (null with one seed) of each job's
point (:func:`efficienttrack.study.ablations.run_variant`): the interaction steps (equal for every variant), the model's
Tr.MPE and Te.MPE, the policy's Po.MAE, every test metric of :func:`~efficienttrack.data.metrics.compute_metrics` and the
wall time. The table shows the paper's columns of the ablation (Table II: Tr.MPE, Te.MPE, MAE; Table III: Po.MAE,
1st oSMT, MAE), the CSV and JSON every field.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import atomic_write, write_csv, write_json
from efficienttrack.data.metrics import TABLE_METRICS
from efficienttrack.study.ablations import ABLATIONS, Ablation
from efficienttrack.study.jobs import STUDY_CONFIG
from efficienttrack.study.report import read_jobs
from efficienttrack.study.summary import stats
from efficienttrack.study.tables import COLUMNS, cell

FIELDS: dict[str, tuple[str, str]] = {
    "interaction_steps": COLUMNS["interaction_steps"],
    "tr_mpe_deg": ("Tr.MPE (°)", ".2f"),
    "te_mpe_deg": ("Te.MPE (°)", ".2f"),
    "po_mae_train_deg": ("Po.MAE, training (°)", ".3f"),
    "po_mae_heldout_deg": ("Po.MAE, held-out (°)", ".3f"),
    **{metric: COLUMNS[metric] for metric in TABLE_METRICS},
    "wall_seconds": COLUMNS["wall_seconds"],
}
"""Every field of a variant's row, with its column heading and number format."""
OUTPUTS = ("ablation.json", "ablation.md", "ablation.csv", "ablation.png")
"""The report's files in the ablation folder."""
NOTES = (
    "Tr.MPE: the model's 20-step prediction error on the training episodes; Te.MPE: on EfficientTrack's test "
    "episodes. Po.MAE: the policy's tracking error as its model predicts it (rollouts of the policy's horizon from "
    'every recorded step), on the training episodes (the paper\'s: "on the model-predicted positions during training") '
    "and on the held-out PD episodes of the test references. MAE, oSMT: EfficientTrack on the test references."
)


@dataclass(frozen=True)
class AblationReport:
    """An ablation's report.

    Attributes:
        ablation: the ablation's name.
        entries: one per variant (``ablation.json``'s ``variants``).
        failed: job name → error, of the jobs with an ``error.json`` and no result.
        markdown: the content of ``ablation.md``.
        paths: the files written.
    """

    ablation: str
    entries: list[dict[str, Any]]
    failed: dict[str, str]
    markdown: str
    paths: tuple[Path, ...]


def job_values(result: dict[str, Any]) -> dict[str, Any]:
    """The fields of an ablation job's one point (:data:`FIELDS`, and ``per_joint_mae_deg``).

    Args:
        result: the job's ``result.json`` content.

    Returns:
        Field → value (None where the point lacks it).
    """
    p = result["curve"][0]
    model, po_mae = p.get("model") or {}, p.get("po_mae") or {}
    return {
        "interaction_steps": p["interaction_steps"],
        "tr_mpe_deg": model.get("tr_mpe_deg"),
        "te_mpe_deg": model.get("te_mpe_deg"),
        "po_mae_train_deg": po_mae.get("train_deg"),
        "po_mae_heldout_deg": po_mae.get("heldout_deg"),
        **{metric: p["metrics"].get(metric) for metric in TABLE_METRICS},
        "wall_seconds": p.get("wall_seconds"),
        "per_joint_mae_deg": p["metrics"].get("per_joint_mae_deg"),
    }


def summarize(ablation: Ablation, results: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """One entry per variant: the mean ± std over seeds of every field.

    Args:
        ablation: the ablation (its default values give the order of the variants; others follow by name).
        results: the jobs' ``result.json`` contents (those without a ``variant`` are left out).

    Returns:
        ``[{"variant", "label", "overrides", "seeds": [int], <field> and <field>_std for each of FIELDS,
        "per_joint_mae_deg": [4], "warnings": [the runs' guard warnings], "jobs": [{"seed", <field>...}]}]``.
    """
    groups: dict[str, list[dict[str, Any]]] = {}
    for result in results:
        if isinstance(result.get("variant"), dict):
            groups.setdefault(result["variant"]["name"], []).append(result)
    order = [ablation.variant(value).name for value in ablation.values]
    entries = []
    for name in sorted(groups, key=lambda n: (order.index(n) if n in order else len(order), n)):
        group = sorted(groups[name], key=lambda r: r["seed"])
        jobs = [{"seed": r["seed"], **job_values(r)} for r in group]
        entry: dict[str, Any] = {**group[0]["variant"], "seeds": [job["seed"] for job in jobs]}
        entry["variant"] = entry.pop("name")
        for field in FIELDS:
            entry[field], entry[f"{field}_std"] = stats([job[field] for job in jobs if job[field] is not None])
        joints = [job["per_joint_mae_deg"] for job in jobs if job["per_joint_mae_deg"] is not None]
        entry["per_joint_mae_deg"] = np.mean(joints, axis=0).tolist() if joints else None
        entry["warnings"] = [p["warning"] for r in group for p in r["curve"] if p.get("warning")]
        entry["jobs"] = jobs
        entries.append(entry)
    return entries


def markdown_table(
    ablation: Ablation, facts: dict[str, Any], entries: Sequence[dict[str, Any]], failed: dict[str, str]
) -> str:
    """The report as Markdown: one row per variant (the ablation's columns, mean ± std over seeds), the paper's values.

    Args:
        ablation: the ablation.
        facts: ``{"preset", "passes"}`` of the ablation's study.
        entries: :func:`summarize`'s entries.
        failed: job name → error.

    Returns:
        The text of ``ablation.md``.
    """
    columns = ("interaction_steps", *ablation.columns)
    headers = ["variant", "seeds", *(FIELDS[field][0] for field in columns)]
    lines = [
        f"# Ablation `{ablation.name}`: {ablation.title}",
        "",
        f"Preset `{facts['preset']}`, {facts['passes']} collection pass{'' if facts['passes'] == 1 else 'es'} for every "
        "variant (equal data); mean ± sample std over seeds.",
        "",
        "| " + " | ".join(headers) + " |",
        "|" + "|".join("---" if i == 0 else "---:" for i in range(len(headers))) + "|",
    ]
    for e in entries:
        cells = [e["label"], str(len(e["seeds"])), *(cell(e[field], e[f"{field}_std"], FIELDS[field][1]) for field in columns)]
        lines.append("| " + " | ".join(cells) + " |")
    if not entries:
        lines += ["", "No job has finished yet."]
    lines += ["", NOTES]
    if ablation.paper:
        paper_columns = [field for field in ablation.columns if any(field in row for row in ablation.paper.values())]
        lines += ["", "The paper's values (the XE75, its settings and data):", ""]
        lines += ["| variant | " + " | ".join(FIELDS[field][0] for field in paper_columns) + " |"]
        lines += ["|---|" + "---:|" * len(paper_columns)]
        for name, row in ablation.paper.items():
            cells = [f"{row[field]:.2f}" if field in row else "–" for field in paper_columns]
            lines.append(f"| {ablation.variant(_value_of(ablation, name)).label} | " + " | ".join(cells) + " |")
    warned = [e["label"] for e in entries if e["warnings"]]
    if warned:
        lines += ["", f"Guard warnings (the figures are mostly the PD controller's) in: {', '.join(warned)}."]
    if failed:
        lines += ["", "## Failed jobs", "", *(f"- `{name}`: {error}" for name, error in sorted(failed.items()))]
    return "\n".join(lines) + "\n"


def _value_of(ablation: Ablation, name: str) -> str:
    """The default value whose variant is called ``name``."""
    return next(value for value in ablation.values if ablation.variant(value).name == name)


def plot_ablation(ablation: Ablation, entries: Sequence[dict[str, Any]], path: str | Path) -> Path:
    """One panel per column of the ablation's table: each variant's mean with ± std error bars, its seeds as dots.

    The paper's values, where it gives them, are hollow diamonds.

    Args:
        ablation: the ablation (its columns and the paper's values).
        entries: :func:`summarize`'s entries.
        path: PNG to write.

    Returns:
        The path written.
    """
    columns = ablation.columns
    fig, axes = plt.subplots(1, len(columns), figsize=(3.4 * len(columns), 3.6), layout="constrained", squeeze=False)
    x = np.arange(len(entries))
    for ax, field in zip(axes[0], columns, strict=True):
        means = np.array([np.nan if e[field] is None else e[field] for e in entries], dtype=float)
        spread = np.array([0.0 if e[f"{field}_std"] is None else e[f"{field}_std"] for e in entries], dtype=float)
        ax.errorbar(x, means, yerr=spread, fmt="o", color="C0", capsize=4, label="mean ± std")
        for i, e in enumerate(entries):
            seeds = [job[field] for job in e["jobs"] if job[field] is not None]
            ax.plot(np.full(len(seeds), i + 0.12), seeds, ".", color="C0", alpha=0.4)
        paper = [(i, ablation.paper[e["variant"]][field]) for i, e in enumerate(entries)
                 if field in ablation.paper.get(e["variant"], {})]  # fmt: skip
        if paper:
            ax.plot(*np.array(paper).T, "D", mfc="none", color="C3", label="paper")
        ax.set_xticks(x, [e["label"] for e in entries], rotation=30, ha="right", fontsize=8)
        ax.set_title(FIELDS[field][0], fontsize=10)
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3, axis="y")
    axes[0][0].legend(fontsize=7)
    fig.suptitle(f"Ablation {ablation.name}", fontsize=11)
    try:
        return atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=100))
    finally:
        plt.close(fig)


def ablation_report(out: str | Path) -> AblationReport:
    """Rebuild an ablation's report from its folder: ``ablation.json``, ``ablation.md``, ``ablation.csv``, ``ablation.png``.

    Args:
        out: the ablation folder (its ``study_config.json`` names the ablation; ``jobs/<name>/result.json``).

    Returns:
        The report.

    Raises:
        EfficientTrackError: ``out`` holds no ablation (no jobs folder, or a ``study_config.json`` of a study).
    """
    out = Path(out)
    results, failed = read_jobs(out)
    try:
        config = json.loads((out / STUDY_CONFIG).read_text())
        ablation = ABLATIONS[config["ablation"]]
        facts = {"preset": config["preset"], "passes": config["run_config"]["collect"]["passes"]}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise EfficientTrackError(f"--out {out}: no ablation here ({STUDY_CONFIG} names none: {exc!r})") from exc
    entries = summarize(ablation, results)
    markdown = markdown_table(ablation, facts, entries, failed)
    fields = [*ablation.columns, *(field for field in FIELDS if field not in ablation.columns)]
    header = ["variant", "label", "seeds", *(name for field in fields for name in (field, f"{field}_std"))]
    rows = ([e["variant"], e["label"], " ".join(map(str, e["seeds"])), *(e[name] for name in header[3:])] for e in entries)
    document = {"ablation": ablation.name, "title": ablation.title, **facts, "variants": entries, "failed": failed}
    paths = (
        write_json(out / "ablation.json", document),
        atomic_write(out / "ablation.md", lambda f: f.write(markdown), mode="w"),
        write_csv(out / "ablation.csv", header, rows),
        plot_ablation(ablation, entries, out / "ablation.png"),
    )
    return AblationReport(ablation.name, entries, failed, markdown, paths)

"""``evaluate``: PD alone and, given a policy, Algorithm 2 on references; and the results both it and a run write.

An evaluation folder holds ``evaluate.json`` (system, references, policy and its SHA-256: a resumed evaluation must
match), ``records/{pd,efficienttrack}/<reference>.npz`` written episode by episode (a rerun after an interruption or a
failure of the system tracks only the rest), ``metrics.json``, ``plots/`` and ``run.log``.
"""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import torch
from rich.console import Console

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import write_json
from efficienttrack.core.provenance import claim_folder, provenance
from efficienttrack.data.metrics import compute_metrics, interaction_hours, metrics_table, rounded
from efficienttrack.data.records import EpisodeRecord
from efficienttrack.data.references import Reference
from efficienttrack.deploy.runtime import check_references
from efficienttrack.learn import policy
from efficienttrack.learn.checkpoints import record_evaluation
from efficienttrack.learn.nets import resolve_device
from efficienttrack.systems.spec import SystemSpec
from efficienttrack.workflow import plots
from efficienttrack.workflow.stages import COLLECT, INTERACTIONS, RunLog, track_and_save

EVALUATE_JSON = "evaluate.json"
"""What an evaluation folder holds: system, references and policy (a resumed evaluation must match)."""
EVALUATE_OUTPUTS = (EVALUATE_JSON, "records", "metrics.json", "plots", "run.log")
"""What :func:`evaluate` writes in its folder: a fresh evaluation deletes these."""
FALLBACK_LIMIT = 0.1
"""Share of the policy's steps on which the guard may fall back to the raw reference (a = 0) before the results are
no longer reported as EfficientTrack's: above it they are mostly the PD controller's."""


def check_plots(max_plots: int | None) -> None:
    """Refuse a negative ``--plots``.

    Args:
        max_plots: the number of references to plot, or None for every one.
    """
    if max_plots is not None and max_plots < 0:
        raise EfficientTrackError(f"--plots {max_plots}: expected a number of references ≥ 0")


def fallback_share(records: Sequence[EpisodeRecord] | None) -> tuple[float | None, str | None]:
    """Share of the policy's steps on which the guard fell back, and a warning when it exceeds :data:`FALLBACK_LIMIT`.

    Args:
        records: the policy's records (``meta["fallbacks"]`` counts each episode's guarded steps), or None.

    Returns:
        (share in [0, 1], warning text or None); (None, None) without records.
    """
    if not records:
        return None, None
    share = sum(r.meta["fallbacks"] for r in records) / max(1, sum(len(r) for r in records))
    if share <= FALLBACK_LIMIT:
        return share, None
    return share, (
        f"the guard fell back to the raw reference (a = 0) on {share:.0%} of the policy's steps: these figures are "
        "mostly the PD controller's, not EfficientTrack's; check the policy (its training, max_adjust) and the system"
    )


def worse_than_pd(pd: dict[str, Any], efficienttrack: dict[str, Any] | None) -> str | None:
    """A warning when the policy tracks worse than the PD controller alone (test MAE), else None.

    Args:
        pd: PD's metrics (:func:`~efficienttrack.data.metrics.compute_metrics`, ``mae_deg``).
        efficienttrack: the policy's, or None without a policy.

    Returns:
        The warning, naming both errors and what to do, or None.
    """
    if efficienttrack is None or efficienttrack["mae_deg"] <= pd["mae_deg"]:
        return None
    return (
        f"the policy tracks worse than PD alone ({efficienttrack['mae_deg']:.2f}° against {pd['mae_deg']:.2f}° MAE on the "
        "test references): do not deploy it; train longer (the cpu preset, or run --time-budget MINUTES) or on more data"
    )


def results(
    system: SystemSpec,
    refs: Sequence[Reference],
    pd_records: list[EpisodeRecord],
    et_records: list[EpisodeRecord] | None,
    *,
    interaction_steps: int | None,
    train_seconds: float | None,
    model: dict[str, float] | None,
    policy_path: str | None,
    config: dict[str, Any] | None,
    device: torch.device | None,
    wall_seconds: float,
) -> dict[str, Any]:
    """The one ``metrics.json`` schema of a run and of :func:`evaluate`.

    Args:
        system: the system evaluated on.
        refs: the references, in the order of the records.
        pd_records: PD alone on ``refs``.
        et_records: the policy on ``refs``, or None without a policy.
        interaction_steps: training interactions of the policy (I.S.), or None when not known.
        train_seconds: the trainings' time, or None.
        model: the model's ``{"tr_mpe_deg", "te_mpe_deg"}``, or None.
        policy_path: the policy's checkpoint, or None.
        config: the run's settings, or None.
        device: where the policy ran (provenance).
        wall_seconds: the command's time so far (provenance).

    Returns:
        ``{"pd", "efficienttrack": compute_metrics' dicts (None without a policy), "interaction_steps",
        "interaction_hours", "train_seconds", "model", "fallbacks", "fallback_share", "warning" (:func:`fallback_share`),
        "worse_than_pd" (:func:`worse_than_pd`), "references", "policy", "system", "config", "rounds": None,
        "gradient_samples": None, "time_budget": None, "provenance"}`` (a run fills ``rounds``, ``gradient_samples`` and
        ``time_budget``).
    """
    share, warning = fallback_share(et_records)
    pd, efficienttrack = (
        rounded(compute_metrics(pd_records)),
        None if et_records is None else rounded(compute_metrics(et_records)),
    )
    return {
        "pd": pd,
        "efficienttrack": efficienttrack,
        "interaction_steps": interaction_steps,
        "interaction_hours": None if interaction_steps is None else round(interaction_hours(interaction_steps), 4),
        "train_seconds": train_seconds,
        "model": model,
        "fallbacks": None if et_records is None else sum(r.meta["fallbacks"] for r in et_records),
        "fallback_share": None if share is None else round(share, 4),
        "warning": warning,
        "worse_than_pd": worse_than_pd(pd, efficienttrack),
        "references": [ref.name for ref in refs],
        "policy": policy_path,
        "system": system.to_dict(),
        "config": config,
        "rounds": None,
        "gradient_samples": None,
        "time_budget": None,
        "provenance": provenance(device, wall_seconds),
    }


def record_verdict(policy_path: str | Path, metrics: dict[str, Any], log: RunLog) -> None:
    """Keep the policy's measured verdict in its own config, so that copies and exports carry it (deploy's gate).

    A config that cannot be written (a read-only copy) gets a warning: the evaluation itself is done and kept.

    Args:
        policy_path: the policy's checkpoint.
        metrics: its evaluation (:func:`results`).
        log: where to warn.
    """
    evaluation = {
        "mae_deg": metrics["efficienttrack"]["mae_deg"],
        "pd_mae_deg": metrics["pd"]["mae_deg"],
        "worse_than_pd": metrics["worse_than_pd"],
        "references": metrics["references"],
        "system": metrics["system"],
        "when": datetime.now(UTC).isoformat(timespec="seconds"),
    }
    try:
        record_evaluation(policy_path, evaluation)
    except EfficientTrackError as exc:
        log.print(f"[bold red]warning: the verdict is not kept with the policy ({exc}); deploy reads metrics.json[/]")


def publish(
    out: Path,
    log: RunLog,
    metrics: dict[str, Any],
    refs: Sequence[Reference],
    pd_records: list[EpisodeRecord],
    et_records: list[EpisodeRecord] | None,
    max_plots: int | None,
    title: str,
) -> None:
    """Write ``metrics.json``, the tracking plots (every reference, or the first ``max_plots``) and print the table.

    Args:
        out: the folder.
        log: where to print.
        metrics: what :func:`results` made.
        refs: the references, in the order of the records.
        pd_records: PD alone on ``refs``.
        et_records: the policy on ``refs``, or None.
        max_plots: plot the first this many references (None: every one).
        title: the table's title (``test``, ``evaluation``).
    """
    write_json(out / "metrics.json", metrics)
    method = "EfficientTrack" if metrics["warning"] is None else "guard fallback (not EfficientTrack)"
    runs = {"PD": pd_records} if et_records is None else {"PD": pd_records, method: et_records}
    for i, ref in enumerate(refs[:max_plots]):
        plots.plot_tracking(
            {name: records[i] for name, records in runs.items()}, out / "plots" / f"tracking_{ref.name}.png", ref.name
        )
    plots.plot_tracking_error(runs, out / "plots" / "tracking_error.png")
    rows = {"PD": metrics["pd"]} if et_records is None else {"PD": metrics["pd"], method: metrics["efficienttrack"]}
    log.print(metrics_table(rows, title=f"{title} ({out})", training_steps={method: metrics["interaction_steps"]}))
    for warning in (metrics["warning"], metrics["worse_than_pd"]):
        if warning is not None:
            log.print(f"[bold red]warning: {warning}[/]")


def _training_interactions(policy_path: Path) -> int | None:
    """Interaction steps used to train the policy at ``policy_path``, when it lies in a run or round folder; else None.

    A run folder notes them in ``stages/collect.json``, a later round's folder in ``stages/interactions.json``.
    """
    for stage in (COLLECT, INTERACTIONS):
        try:
            steps = json.loads((policy_path.parent / "stages" / f"{stage}.json").read_text()).get("interaction_steps")
        except (OSError, ValueError, AttributeError):
            continue
        if isinstance(steps, int) and not isinstance(steps, bool):
            return steps
    return None


def evaluate(
    system: SystemSpec,
    refs: Sequence[Reference],
    out: str | Path,
    policy_path: str | Path | None = None,
    device: str = "auto",
    console: Console | None = None,
    max_plots: int | None = None,
) -> dict[str, Any]:
    """The PD controller alone and, given a policy, Algorithm 2 on the same references; written like a run's results.

    Writes ``OUT/evaluate.json`` (system, references, policy and its SHA-256) first, then
    ``OUT/records/{pd,efficienttrack}/<reference>.npz`` episode by episode (a rerun after an interruption or
    a failure of the system resumes with the episodes not yet recorded), ``OUT/metrics.json`` (the schema of
    :func:`run_pipeline`), ``OUT/plots/`` (tracking per reference, tracking error over time) and
    appends to ``OUT/run.log``.

    Args:
        system: how to build the closed-loop system.
        refs: the references to track.
        out: the output folder.
        policy_path: a policy checkpoint (``policy.pt``) or None for the PD controller alone.
        device: torch device for the policy (``auto``, ``cpu``, ``cuda``).
        console: where to print the table (the same text goes to ``OUT/run.log``).
        max_plots: draw the tracking plots of the first ``max_plots`` references (None: every one).

    Returns:
        The content of ``metrics.json``: as :func:`run_pipeline`'s, with ``efficienttrack``, ``fallbacks`` and
        ``fallback_share`` null without a policy, ``model``, ``config`` and ``train_seconds`` null, and ``interaction_steps`` /
        ``interaction_hours`` those of the run the policy comes from when it lies in a run folder (else null).

    Raises:
        EfficientTrackError: no references, one outside the joint limits, a missing policy file, a bad device, a
            negative ``max_plots``, ``out`` holding another evaluation, or the system failing on an episode (the
            message names it).
    """
    start = time.perf_counter()
    if not refs:
        raise EfficientTrackError("evaluate: needs at least one reference")
    check_plots(max_plots)
    out = Path(out)
    env = system.open()
    check_references(refs, env.limits)
    pi, torch_device = None, None
    if policy_path is not None:
        if not Path(policy_path).is_file():
            raise EfficientTrackError(f"--policy {policy_path}: no such file")
        torch_device = resolve_device(device)
        pi = policy.load_policy(policy_path).to(torch_device)
    identity = {
        "system": system.to_dict(),
        "references": {ref.name: len(ref.q) for ref in refs},
        "policy": None if policy_path is None else str(Path(policy_path).resolve()),
        "policy_sha256": None if policy_path is None else hashlib.sha256(Path(policy_path).read_bytes()).hexdigest(),
    }
    claim_folder(
        out / EVALUATE_JSON,
        identity,
        "this folder holds an evaluation with another system, references or policy; use another --out, or --force",
    )
    log = RunLog(out, console)
    log.header("evaluate")
    pd_records = track_and_save("pd", out, env, None, refs, None)
    et_records = None if pi is None else track_and_save("efficienttrack", out, env, pi, refs, torch_device)
    metrics = results(
        system,
        refs,
        pd_records,
        et_records,
        interaction_steps=None if policy_path is None else _training_interactions(Path(policy_path)),
        train_seconds=None,
        model=None,
        policy_path=None if policy_path is None else str(policy_path),
        config=None,
        device=torch_device,
        wall_seconds=time.perf_counter() - start,
    )
    publish(out, log, metrics, refs, pd_records, et_records, max_plots, "evaluation")
    if policy_path is not None:
        record_verdict(policy_path, metrics, log)
    return metrics

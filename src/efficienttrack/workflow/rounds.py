"""The rounds of a run: collect or deploy, train g_θ and π_φ, evaluate; and their table.

Round 1 trains on the collection (Algorithm 1). Round k ≥ 2 deploys π_{k−1} on the training references (one pass, no
noise, as the paper's real-machine rounds; or on a share of them, ``round_share``: :func:`round_references`), then
trains g_θ and π_φ starting from θ_{k−1} and φ_{k−1} (warm starts, with their feature scaling) on every episode
recorded so far (``round_data = "all"``) or on the new pass only (``"new"``, the paper's choice), ``warm_budget`` ×
round 1's optimizer steps, as the ``round`` command does (:func:`~efficienttrack.workflow.next_round.continued_config`).
Round k ≥ 2 lives in ``OUT/rounds/<k>/``, laid out as a run folder, with its own ``stages/``::

    OUT/rounds/<k>/records/deploy/          π_{k−1} on the training references: the round's new data
    OUT/rounds/<k>/model.pt, policy.pt      θ_k, φ_k (configs beside them); checkpoints/, logs/ while training
    OUT/rounds/<k>/records/efficienttrack/  π_k on the test references

The rounds table has the columns of the paper's Table IV: interactions used for training so far (I.S., I.T.),
1st/2nd-order smoothness, MAE, RMSE, FMAE, ETD-MAE, ETD-FMAE, and the model's Tr.MPE / Te.MPE.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import Any, NamedTuple

import torch
from rich.table import Table

from efficienttrack.core.fileio import atomic_write, write_csv
from efficienttrack.data.metrics import compute_metrics, interaction_hours, rounded
from efficienttrack.data.records import EpisodeRecord
from efficienttrack.data.references import Reference
from efficienttrack.learn import dynamics, policy
from efficienttrack.learn.dynamics import ClosedLoopModel
from efficienttrack.learn.policy import AdjustmentPolicy
from efficienttrack.learn.settings import TrainingSchedule
from efficienttrack.systems.protocol import BatchedSystem
from efficienttrack.workflow.config import RunConfig
from efficienttrack.workflow.ledger import Ledger
from efficienttrack.workflow.next_round import ConfigT, continued_config
from efficienttrack.workflow.stages import INTERACTIONS, RunLog, evaluate_stage, train_stage
from efficienttrack.workflow.time_budget import Planner

TABLE_COLUMNS = (
    ("I.S.", "interaction_steps", "{:d}"),
    ("I.T. (h)", "interaction_hours", "{:.2f}"),
    ("1st oSMT °", "smt1_deg", "{:.2f}"),
    ("2nd oSMT °", "smt2_deg", "{:.2f}"),
    ("MAE °", "mae_deg", "{:.2f}"),
    ("RMSE °", "rmse_deg", "{:.2f}"),
    ("FMAE °", "fmae_deg", "{:.2f}"),
    ("ETD-MAE cm", "etd_mae_cm", "{:.2f}"),
    ("ETD-FMAE cm", "etd_fmae_cm", "{:.2f}"),
    ("Tr.MPE °", "tr_mpe_deg", "{:.3f}"),
    ("Te.MPE °", "te_mpe_deg", "{:.3f}"),
)
"""The rounds table's columns: heading, key of a row, format (the paper's Table IV, plus the model's errors)."""


class Run(NamedTuple):
    """What every round of a run shares.

    Attributes:
        cfg: the run's settings.
        system: the closed-loop system.
        train_refs: the training references (round k ≥ 2 deploys on them once, without noise).
        test_refs: the held-out references.
        held_out: episodes for the held-out figures of the training logs (PD on the test references).
        ledger: the run's finished stages and time.
        planner: the factor on each training's steps (1 without a time budget).
        log: the run's console log.
        device: where the networks run.
    """

    cfg: RunConfig
    system: BatchedSystem
    train_refs: Sequence[Reference]
    test_refs: Sequence[Reference]
    held_out: Sequence[EpisodeRecord]
    ledger: Ledger
    planner: Planner
    log: RunLog
    device: torch.device


class RoundState(NamedTuple):
    """Where a round leaves off: what the next one starts from (before round 1: the collection, no networks).

    Attributes:
        g_theta: the round's closed-loop dynamics model.
        pi_phi: the round's adjustment policy.
        records: every training episode recorded up to this round (collection, then each deployment pass).
        interaction_steps: steps the machine was driven for training up to this round (I.S.).
        test_records: the round's policy on the test references.
        summary: the round's entry of ``metrics.json``'s ``rounds`` (:func:`round_summary`).
        facts: the training stages' facts of the round, ``{"model": {...}, "policy": {...}}`` (seconds, log folder).
    """

    g_theta: ClosedLoopModel | None
    pi_phi: AdjustmentPolicy | None
    records: list[EpisodeRecord]
    interaction_steps: int
    test_records: list[EpisodeRecord]
    summary: dict[str, Any]
    facts: dict[str, dict[str, Any]]


def round_summary(
    k: int,
    interaction_steps: int,
    test_records: Sequence[EpisodeRecord],
    g_theta: ClosedLoopModel,
    train_records: Sequence[EpisodeRecord],
    train_seconds: float,
    gradient_samples: int | None,
) -> dict[str, Any]:
    """One round's entry of ``metrics.json``'s ``rounds`` list.

    Args:
        k: the round, from 1.
        interaction_steps: training interactions up to and including this round (I.S.).
        test_records: the round's policy on the test references.
        g_theta: the round's model.
        train_records: what the round trained on (for Tr.MPE).
        train_seconds: the round's model and policy training time, s.
        gradient_samples: the windows the round's optimizer steps took, both trainings (:func:`gradient_samples`).

    Returns:
        ``{"round", "interaction_steps", "interaction_hours", "train_seconds", "gradient_samples", "efficienttrack": {metrics},
        "model": {"tr_mpe_deg", "te_mpe_deg"}}``.
    """
    return {
        "round": k,
        "interaction_steps": interaction_steps,
        "interaction_hours": round(interaction_hours(interaction_steps), 4),
        "train_seconds": round(train_seconds, 2),
        "gradient_samples": gradient_samples,
        "efficienttrack": rounded(compute_metrics(test_records)),
        "model": {
            "tr_mpe_deg": round(float(dynamics.model_error(g_theta, train_records).mpe_deg), 4),
            "te_mpe_deg": round(float(dynamics.model_error(g_theta, test_records).mpe_deg), 4),
        },
    }


def run_round(k: int, previous: RoundState, run: Run) -> RoundState:
    """Round k (resumable stage by stage): deploy π_{k−1} (k ≥ 2), train g_θ, then π_φ through it, evaluate π_φ.

    Args:
        k: the round, from 1.
        previous: where round k − 1 left off (before round 1: the collected records, no networks).
        run: what the rounds share.

    Returns:
        Where round k leaves off.
    """
    cfg, ledger, device = run.cfg, run.ledger, run.device
    deployed: list[EpisodeRecord] = []
    if k > 1:
        refs = round_references(run.train_refs, k, cfg.round_share)
        which = "the" if len(refs) == len(run.train_refs) else f"{len(refs)} of the"
        run.log.print(f"round {k}: deploying the round-{k - 1} policy on {which} {len(run.train_refs)} training references")
        deployed = evaluate_stage(ledger, k, "deploy", run.system, previous.pi_phi, refs, device)
    records = [*previous.records, *deployed]
    train_records = deployed if k > 1 and cfg.round_data == "new" else records
    common: dict[str, Any] = {"device": device, "seed": cfg.seed, "held_out": run.held_out}

    def share(part: str) -> float:  # of round 1's steps, planned when the training is about to begin
        return run.planner.scale(k, part) * (1.0 if k == 1 else cfg.warm_budget)

    g_cfg = _warm(cfg.model.scaled(share("model")), None if previous.g_theta is None else previous.g_theta.cfg, cfg)
    trainer: partial[Any] = partial(dynamics.train_model, g_cfg, train_records, init=previous.g_theta, **common)
    g_theta, model_facts = train_stage(ledger, k, "model", run.log, trainer, dynamics.save_model, dynamics.load_model, device)
    pi_cfg = _warm(cfg.policy.scaled(share("policy")), None if previous.pi_phi is None else previous.pi_phi.cfg, cfg)
    trainer = partial(policy.train_policy, pi_cfg, g_theta, train_records, init=previous.pi_phi, **common)
    pi_phi, policy_facts = train_stage(ledger, k, "policy", run.log, trainer, policy.save_policy, policy.load_policy, device)
    test_records = evaluate_stage(ledger, k, "efficienttrack", run.system, pi_phi, run.test_refs, device)
    steps = previous.interaction_steps + sum(len(r) for r in deployed)
    seconds = model_facts["seconds"] + policy_facts["seconds"]
    samples = add_samples(gradient_samples(model_facts, g_cfg), gradient_samples(policy_facts, pi_cfg))
    summary = round_summary(k, steps, test_records, g_theta, train_records, seconds, samples)
    if k > 1:
        ledger.once(INTERACTIONS, lambda: {"interaction_steps": steps}, k, ("interaction_steps",))
        run.log.print(f"round {k}: test MAE {summary['efficienttrack']['mae_deg']:.3f}° after {steps} interaction steps")
    return RoundState(g_theta, pi_phi, records, steps, test_records, summary, {"model": model_facts, "policy": policy_facts})


def round_references(refs: Sequence[Reference], k: int, share: float) -> list[Reference]:
    """The training references round k ≥ 2 deploys on: ``ceil(share · n)`` of the n, the window after round k − 1's.

    Args:
        refs: the training references, in order.
        k: the round, from 2.
        share: :attr:`~efficienttrack.workflow.config.RunConfig.round_share`.

    Returns:
        All of them for ``share`` 1; else the next ``ceil(share · n)``, wrapping around.
    """
    count = min(len(refs), max(1, math.ceil(share * len(refs) - 1e-9)))
    return [refs[((k - 2) * count + i) % len(refs)] for i in range(count)]


def gradient_samples(facts: dict[str, Any], cfg: TrainingSchedule) -> int | None:
    """The windows a training stage's optimizer steps took (steps × batch), or None for a stage that did not keep its steps.

    Args:
        facts: the stage's facts (:func:`~efficienttrack.workflow.stages.train_stage`).
        cfg: the schedule it trained with.
    """
    return None if facts.get("steps") is None else int(facts["steps"]) * cfg.batch_size


def add_samples(*counts: int | None) -> int | None:
    """The sum of gradient-sample counts, or None when one of them is unknown."""
    return None if any(c is None for c in counts) else sum(c for c in counts if c is not None)


def _warm(config: ConfigT, previous: ConfigT | None, run: RunConfig) -> ConfigT:
    """A later round's ``config``: the network's sizes it continues (:func:`continued_config`), ``round_warmup`` its ramp.

    Round 1's (``previous`` None) is ``config`` as it is.
    """
    if previous is None:
        return config
    return replace(continued_config(config, previous), warmup=run.round_warmup)


def rounds_rows(pd: dict[str, Any], rounds: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """The rounds table as rows: the PD controller alone, then every round.

    Args:
        pd: the PD controller's metrics on the test references (:func:`~efficienttrack.data.metrics.compute_metrics`).
        rounds: the rounds' entries (:func:`round_summary`).

    Returns:
        One flat dict per row: ``"method"`` and the keys of :data:`TABLE_COLUMNS` (None where not defined, e.g.
        the PD controller's interactions and model errors).
    """
    keys = [key for _, key, _ in TABLE_COLUMNS]
    rows = [{"method": "PD", **{key: pd.get(key) for key in keys}}]
    for entry in rounds:
        flat = {
            **entry["efficienttrack"],
            **entry["model"],
            **{k: entry[k] for k in ("interaction_steps", "interaction_hours")},
        }
        rows.append({"method": f"Round {entry['round']}", **{key: flat.get(key) for key in keys}})
    return rows


def _cell(value: Any, fmt: str) -> str:
    return "–" if value is None else fmt.format(value)


def rounds_table(rows: Sequence[dict[str, Any]], title: str) -> Table:
    """A rich table of :func:`rounds_rows`, the columns of the paper's Table IV.

    Args:
        rows: the rows.
        title: the table's title.
    """
    table = Table(title=title, caption="test references; I.S./I.T.: training interactions so far (steps, h at 20 Hz)")
    table.add_column("method", no_wrap=True)
    for heading, _, _ in TABLE_COLUMNS:
        table.add_column(heading, justify="right", no_wrap=True)
    for row in rows:
        table.add_row(row["method"], *(_cell(row[key], fmt) for _, key, fmt in TABLE_COLUMNS))
    return table


def write_rounds(rows: Sequence[dict[str, Any]], folder: Path) -> tuple[Path, Path]:
    """Write the rounds table as ``rounds.csv`` (full precision) and ``rounds.md`` (as printed), atomically.

    Args:
        rows: the rows (:func:`rounds_rows`).
        folder: where to write.

    Returns:
        The CSV and Markdown paths.
    """
    keys = ["method", *(key for _, key, _ in TABLE_COLUMNS)]
    csv_path = write_csv(folder / "rounds.csv", keys, ([row[key] for key in keys] for row in rows))
    headings = ["method", *(heading for heading, _, _ in TABLE_COLUMNS)]
    lines = ["| " + " | ".join(headings) + " |", "|---" + "|---:" * len(TABLE_COLUMNS) + "|"]
    lines += [
        "| " + " | ".join([row["method"], *(_cell(row[key], fmt) for _, key, fmt in TABLE_COLUMNS)]) + " |" for row in rows
    ]
    md_path = atomic_write(folder / "rounds.md", lambda f: f.write("\n".join(lines) + "\n"), mode="w")
    return csv_path, md_path

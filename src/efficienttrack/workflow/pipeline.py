"""collect → train model → train policy → evaluate PD and EfficientTrack: one resumable run.

Output folder layout (everything written atomically)::

    OUT/run.json                    what the run is: config, system, references (a rerun must match)
    OUT/config.json                 the RunConfig (also next to every checkpoint and result)
    OUT/records/train/pass_<k>/     Algorithm 1 records, a pass at a time
    OUT/model.pt, model.json        g_θ (state dict + config);  OUT/checkpoints/model.ckpt while training
    OUT/policy.pt, policy.json      π_φ;                        OUT/checkpoints/policy.ckpt while training
    OUT/logs/{model,policy}/        scalars.csv and TensorBoard events of each training (docs/logged-metrics.md)
    OUT/records/{pd,efficienttrack}/<reference>.npz
    OUT/stages/<stage>.json         written last by each finished stage (its facts: seconds, log folder)
    OUT/stages/time_spent.json      the run's wall time over all its invocations (:mod:`efficienttrack.workflow.ledger`)
    OUT/metrics.json                PD and EfficientTrack metrics, training interactions, provenance
    OUT/plots/*.png                 tracking per test reference, tracking error over time, training curves
    OUT/run.log                     what the console showed, plain text, a header line per invocation
    OUT/rounds/<k>/                 round k ≥ 2 of a run with ``rounds`` > 1 (:mod:`efficienttrack.workflow.rounds`)
    OUT/rounds.csv, rounds.md       the rounds table (the paper's Table IV columns); OUT/plots/rounds.png

Held-out figures during training: the PD controller alone is run on the test references first (it is the
baseline, and does not depend on training), and its records are the held-out episodes of both trainings:
the model's 20-step MPE and the policy's model-predicted tracking error on them are logged every
``eval_every`` steps. Training uses all collected episodes, as in the paper; the held-out episodes are
unseen references, under the position controller alone. Each evaluation uses at most
``training.HELD_OUT_STEPS`` recorded steps; with the demo's settings they add 0.7 % to the model's and 2.7 % to
the policy's training time (docs/logged-metrics.md).

With ``time_budget`` (minutes), each training's steps are scaled to fit the rest of the run into it, planned just
before it (:mod:`efficienttrack.workflow.time_budget`); ``metrics.json`` gets ``"time_budget"`` (null without a budget).

A rerun with the same run.json skips every finished stage; an interrupted stage resumes
(collection at its first unwritten pass, training from its checkpoint). A rerun with other
settings into the same folder is refused, except for the number of rounds: a rerun with more
rounds adds them to the finished ones.

:func:`evaluate` writes the same ``metrics.json`` schema (``efficienttrack`` null without a policy;
``model``, ``config``, ``train_seconds`` null), records, tracking plots and ``run.log``; its ``evaluate.json``
names the system, references and policy, so that an interrupted evaluation resumes with the episodes not
yet recorded (each is written as soon as it has run, :func:`efficienttrack.workflow.stages.track_and_save`).
``config.json``, ``run.json`` and ``metrics.json`` carry a ``provenance`` entry
(:func:`efficienttrack.core.provenance.provenance`); run.json's is left out when comparing a rerun.
"""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from functools import partial
from pathlib import Path
from typing import Any

import torch
from rich.console import Console

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import write_json
from efficienttrack.core.provenance import claim_folder, provenance
from efficienttrack.data.cycles import generate_references
from efficienttrack.data.metrics import compute_metrics, interaction_hours, metrics_table, rounded
from efficienttrack.data.records import EpisodeRecord
from efficienttrack.data.references import Reference, references_sha256, save_references
from efficienttrack.deploy.runtime import check_references
from efficienttrack.learn import dynamics, policy
from efficienttrack.learn.checkpoints import record_evaluation
from efficienttrack.learn.nets import resolve_device
from efficienttrack.learn.training import read_scalars
from efficienttrack.systems.protocol import BatchedSystem
from efficienttrack.systems.spec import SystemSpec
from efficienttrack.workflow import plots
from efficienttrack.workflow.collect import collect
from efficienttrack.workflow.config import DEMO, RunConfig
from efficienttrack.workflow.ledger import Ledger
from efficienttrack.workflow.rounds import RoundState, Run, rounds_rows, rounds_table, run_round, write_rounds
from efficienttrack.workflow.stages import COLLECT, INTERACTIONS, RunLog, evaluate_stage, track_and_save
from efficienttrack.workflow.time_budget import Planner, measure_step_times

DEMO_REFERENCES = 40
"""Loading cycles the demo generates (train + test)."""
DEMO_TRAIN = 32
"""The first references of the demo are for training, the rest are held out."""
DEMO_SEED = 2025
"""Seed of the demo's reference generator."""
RUN_OUTPUTS = (
    "run.json",
    "config.json",
    "records",
    "model.pt",
    "model.json",
    "policy.pt",
    "policy.json",
    "checkpoints",
    "stages",
    "metrics.json",
    "plots",
    "logs",
    "run.log",
    "rounds",
    "rounds.csv",
    "rounds.md",
)
"""What :func:`run_pipeline` writes in its folder (see the module docstring): a fresh start deletes these."""
DEMO_OUTPUTS = (*RUN_OUTPUTS, "refs")
"""What :func:`demo` writes in its folder: the run's outputs and the generated references."""
EVALUATE_JSON = "evaluate.json"
"""What an evaluation folder holds: system, references and policy (a resumed evaluation must match)."""
EVALUATE_OUTPUTS = (EVALUATE_JSON, "records", "metrics.json", "plots", "run.log")
"""What :func:`evaluate` writes in its folder: a fresh evaluation deletes these."""
FALLBACK_LIMIT = 0.1
"""Share of the policy's steps on which the guard may fall back to the raw reference (a = 0) before the results are
no longer reported as EfficientTrack's: above it they are mostly the PD controller's."""


@dataclass(frozen=True)
class RunResult:
    """Outcome of :func:`run_pipeline`.

    Attributes:
        out: the output folder.
        metrics: the content of ``OUT/metrics.json``.
        skipped: names of the stages found finished and skipped.
    """

    out: Path
    metrics: dict[str, Any]
    skipped: tuple[str, ...]


def _check_plots(max_plots: int | None) -> None:
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


def _metrics(
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
    """The one ``metrics.json`` schema of :func:`run_pipeline` and :func:`evaluate` (see their Returns)."""
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
        "time_budget": None,
        "provenance": provenance(device, wall_seconds),
    }


def _record_evaluation(policy_path: str | Path, metrics: dict[str, Any], log: RunLog) -> None:
    """Keep the policy's measured verdict in its own config, so that copies and exports carry it (deploy's gate).

    A config that cannot be written (a read-only copy) gets a warning: the evaluation itself is done and kept.
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


def _publish(
    out: Path,
    log: RunLog,
    metrics: dict[str, Any],
    refs: Sequence[Reference],
    pd_records: list[EpisodeRecord],
    et_records: list[EpisodeRecord] | None,
    max_plots: int | None,
    title: str,
) -> None:
    """Write ``metrics.json``, the tracking plots (every reference, or the first ``max_plots``) and print the table."""
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


def run_pipeline(
    system: SystemSpec,
    train_refs: Sequence[Reference],
    test_refs: Sequence[Reference],
    out: str | Path,
    cfg: RunConfig,
    console: Console | None = None,
    max_plots: int | None = None,
    command: str = "run",
) -> RunResult:
    """The whole method on one system: Algorithm 1, model and policy training, Algorithm 2 vs PD.

    Args:
        system: how to build the closed-loop system (any ``module:callable``, no tuning needed).
        train_refs: references for data collection and training.
        test_refs: held-out references for evaluation.
        out: output folder (see the module docstring); a rerun resumes here.
        cfg: the run's settings.
        console: where to print progress notes and the table (a fresh rich console when None); the same
            text is appended to ``OUT/run.log``.
        max_plots: draw the tracking plots of the first ``max_plots`` test references (None: every one).
        command: the command named in this invocation's header line of ``OUT/run.log``.

    Returns:
        The folder, the metrics written to ``OUT/metrics.json`` and the skipped stages of round 1. The metrics
        are those of the last round: ``{"pd", "efficienttrack": compute_metrics' dicts of the test episodes,
        "interaction_steps" and "interaction_hours": training interactions of every round so far, "train_seconds",
        "model": {"tr_mpe_deg", "te_mpe_deg"}, "fallbacks": guard fallbacks, "fallback_share": their share of the
        policy's steps, "warning": None, or why the figures are not EfficientTrack's (:func:`fallback_share`),
        "worse_than_pd": None, or a warning that the policy tracks worse than PD alone (:func:`worse_than_pd`),
        "references": test reference names, "policy": the policy checkpoint, "system", "config", "rounds": one entry per round
        (:func:`efficienttrack.workflow.rounds.round_summary`), "time_budget": None, or the budget's minutes, factors, step
        times and seconds spent (:meth:`~efficienttrack.workflow.time_budget.TimeBudget.summary`), "provenance"}``.

    Raises:
        EfficientTrackError: bad system spec, no references, one outside the joint limits, a negative ``max_plots``, or
            ``out`` holding another run.
    """
    start = time.perf_counter()
    if not train_refs or not test_refs:
        raise EfficientTrackError("run: needs at least one training and one test reference")
    _check_plots(max_plots)
    out = Path(out)
    env = system.open()
    check_references([*train_refs, *test_refs], env.limits)  # before collection moves the machine
    identity = {
        "config": {key: value for key, value in cfg.to_dict().items() if key != "rounds"},  # more rounds extend a run
        "system": system.to_dict(),
        "train_references": {ref.name: len(ref.q) for ref in train_refs},
        "test_references": {ref.name: len(ref.q) for ref in test_refs},
        "references_sha256": references_sha256([*train_refs, *test_refs]),
    }
    device = resolve_device(cfg.device)
    claim_folder(
        out / "run.json",
        identity,
        "this folder holds a run with other settings, system or references; use another --out, or --force to start afresh",
    )
    write_json(out / "config.json", {**cfg.to_dict(), "provenance": provenance(device)})
    log = RunLog(out, console)
    log.header(command)
    ledger = Ledger(out, start)  # counts earlier invocations' time too
    with ledger.counting():
        collecting = partial(_collect, env, train_refs, cfg, out)
        records, facts = ledger.run(COLLECT, collecting, lambda: collecting()[0], keys=("interaction_steps",))
        log.print(f"collected {len(records)} episodes, {facts['interaction_steps']} interaction steps")
        # the PD controller alone on the test references: the baseline, and the held-out episodes of both trainings
        pd_records = evaluate_stage(ledger, 1, "pd", env, None, test_refs, device)
        planner = Planner(cfg, ledger, log, partial(measure_step_times, cfg, records, pd_records, device))
        run = Run(cfg, env, train_refs, test_refs, pd_records, ledger, planner, log, device)
        state = RoundState(None, None, records, facts["interaction_steps"], [], {}, {})
        summaries = []
        for k in range(1, cfg.rounds + 1):
            state = run_round(k, state, run)
            summaries.append(state.summary)
        metrics = _report(run, state, summaries, system, max_plots, start)
    return RunResult(out=out, metrics=metrics, skipped=tuple(ledger.skipped))


def _collect(
    env: BatchedSystem, refs: Sequence[Reference], cfg: RunConfig, out: Path
) -> tuple[list[EpisodeRecord], dict[str, Any]]:
    """Algorithm 1 (resumes pass by pass): the records and the collection's facts."""
    collected = collect(env, refs, cfg.collect, out / "records" / "train")
    return collected.records, {"interaction_steps": collected.interaction_steps}


def _report(
    run: Run, state: RoundState, summaries: list[dict[str, Any]], system: SystemSpec, max_plots: int | None, start: float
) -> dict[str, Any]:
    """The last round's results: ``metrics.json``, plots, the tables, and the verdict kept with the policy."""
    cfg, out = run.cfg, run.ledger.out
    folder = run.ledger.folder(cfg.rounds)
    metrics = _metrics(
        system,
        run.test_refs,
        list(run.held_out),
        state.test_records,
        interaction_steps=state.interaction_steps,
        train_seconds=round(sum(entry["train_seconds"] for entry in summaries), 2),
        model=state.summary["model"],
        policy_path=str(folder / "policy.pt"),
        config=cfg.to_dict(),
        device=run.device,
        wall_seconds=time.perf_counter() - start,
    )
    metrics["rounds"] = summaries
    metrics["time_budget"] = run.planner.summary()
    curves = {
        name: plots.TrainingCurves(read_scalars(folder / state.facts[name]["log"]), *labels)
        for name, labels in (
            ("model", (dynamics.LOSS_LABEL, dynamics.HELD_OUT_TAG, dynamics.HELD_OUT_LABEL)),
            ("policy", (policy.LOSS_LABEL, policy.HELD_OUT_TAG, policy.HELD_OUT_LABEL)),
        )
    }
    plots.plot_training_curves(curves, out / "plots" / "training_curves.png")
    _publish(out, run.log, metrics, run.test_refs, list(run.held_out), state.test_records, max_plots, "test")
    _record_evaluation(folder / "policy.pt", metrics, run.log)
    if cfg.rounds > 1:
        rows = rounds_rows(metrics["pd"], summaries)
        write_rounds(rows, out)
        plots.plot_rounds(rows, out / "plots" / "rounds.png")
        run.log.print(rounds_table(rows, title=f"rounds ({out})"))
    return metrics


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
    _check_plots(max_plots)
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
    metrics = _metrics(
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
    _publish(out, log, metrics, refs, pd_records, et_records, max_plots, "evaluation")
    if policy_path is not None:
        _record_evaluation(policy_path, metrics, log)
    return metrics


def demo(
    out: str | Path = "runs/demo", cfg: RunConfig | None = None, console: Console | None = None, max_plots: int | None = None
) -> RunResult:
    """The whole method on the built-in ``xe75`` simulator with generated references.

    Draws ``DEMO_REFERENCES`` loading cycles (fixed seed), trains on the first ``DEMO_TRAIN`` and
    tests on the rest; the references are saved under ``OUT/refs/{train,test}``.

    Args:
        out: output folder (resumable like :func:`run_pipeline`).
        cfg: the run's settings; ``config.DEMO`` when None.
        console: where to print (the same text goes to ``OUT/run.log``).
        max_plots: draw the tracking plots of the first ``max_plots`` test references (None: every one).

    Returns:
        The result of :func:`run_pipeline`.
    """
    refs = generate_references(DEMO_REFERENCES, seed=DEMO_SEED)
    train, test = refs[:DEMO_TRAIN], refs[DEMO_TRAIN:]
    save_references(train, Path(out) / "refs" / "train")
    save_references(test, Path(out) / "refs" / "test")
    start = time.perf_counter()
    result = run_pipeline(SystemSpec(), train, test, out, cfg or DEMO, console, max_plots, command="demo")
    ratio = result.metrics["efficienttrack"]["mae_deg"] / result.metrics["pd"]["mae_deg"]
    method = "EfficientTrack" if result.metrics["warning"] is None else "guard fallback (not EfficientTrack)"
    RunLog(Path(out), console).print(
        f"{method} MAE = {ratio:.2f} × PD MAE; wall time {time.perf_counter() - start:.0f} s; outputs in {out}"
    )
    return result

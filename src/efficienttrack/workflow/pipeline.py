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

The PD controller alone runs on the test references first: it is the baseline, and its records are the held-out
episodes whose figures both trainings log (docs/logged-metrics.md). A rerun with the same ``run.json`` skips every
finished stage and resumes an interrupted one; one with other settings is refused, except for more rounds, which are
added to the finished ones. With ``time_budget`` each training is planned to fit (:mod:`efficienttrack.workflow.time_budget`).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

from rich.console import Console

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import write_json
from efficienttrack.core.provenance import claim_folder, provenance
from efficienttrack.data.cycles import generate_references
from efficienttrack.data.records import EpisodeRecord
from efficienttrack.data.references import Reference, references_sha256, save_references
from efficienttrack.deploy.runtime import check_references
from efficienttrack.learn import dynamics, policy
from efficienttrack.learn.nets import resolve_device
from efficienttrack.learn.training import read_scalars
from efficienttrack.systems.protocol import BatchedSystem
from efficienttrack.systems.spec import SystemSpec
from efficienttrack.workflow import plots
from efficienttrack.workflow.collect import collect
from efficienttrack.workflow.config import DEMO, RunConfig
from efficienttrack.workflow.evaluation import check_plots, publish, record_verdict, results
from efficienttrack.workflow.ledger import Ledger
from efficienttrack.workflow.rounds import (
    RoundState,
    Run,
    add_samples,
    rounds_rows,
    rounds_table,
    run_round,
    write_rounds,
)
from efficienttrack.workflow.stages import COLLECT, RunLog, evaluate_stage
from efficienttrack.workflow.time_budget import Planner, measure_step_times

DEMO_REFERENCES = 40
"""Loading cycles the demo generates (train + test)."""
DEMO_TRAIN = 32
"""The first references of the demo are for training, the rest are held out."""
DEMO_SEED = 2025
"""Seed of the demo's reference generator."""
RUN_OUTPUTS = (
    "run.json", "config.json", "records", "model.pt", "model.json", "policy.pt", "policy.json", "checkpoints", "stages",
    "metrics.json", "plots", "logs", "run.log", "rounds", "rounds.csv", "rounds.md",
)  # fmt: skip
"""What :func:`run_pipeline` writes in its folder (see the module docstring): a fresh start deletes these."""
DEMO_OUTPUTS = (*RUN_OUTPUTS, "refs")
"""What :func:`demo` writes in its folder: the run's outputs and the generated references."""


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
        The folder, the last round's metrics as written to ``OUT/metrics.json``
        (:func:`~efficienttrack.workflow.evaluation.results`, with ``"rounds"``: one
        :func:`~efficienttrack.workflow.rounds.round_summary` per round, and ``"time_budget"``) and the stages found finished.

    Raises:
        EfficientTrackError: bad system spec, no references, one outside the joint limits, a negative ``max_plots``, or
            ``out`` holding another run.
    """
    start = time.perf_counter()
    if not train_refs or not test_refs:
        raise EfficientTrackError("run: needs at least one training and one test reference")
    check_plots(max_plots)
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
    metrics = results(
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
    metrics["gradient_samples"] = add_samples(*(entry["gradient_samples"] for entry in summaries))
    metrics["time_budget"] = run.planner.summary()
    measured = {
        "PD, measured test MAE": metrics["pd"]["mae_deg"],
        "policy, measured test MAE": state.summary["efficienttrack"]["mae_deg"],
    }
    curves = {
        "model": plots.TrainingCurves(read_scalars(folder / state.facts["model"]["log"]), dynamics.LOSS_LABEL,
                                      dynamics.HELD_OUT_TAG, dynamics.HELD_OUT_LABEL),
        "policy": plots.TrainingCurves(read_scalars(folder / state.facts["policy"]["log"]), policy.LOSS_LABEL,
                                       policy.HELD_OUT_TAG, policy.HELD_OUT_LABEL, measured),
    }  # fmt: skip
    plots.plot_training_curves(curves, out / "plots" / "training_curves.png")
    publish(out, run.log, metrics, run.test_refs, list(run.held_out), state.test_records, max_plots, "test")
    record_verdict(folder / "policy.pt", metrics, run.log)
    if cfg.rounds > 1:
        rows = rounds_rows(metrics["pd"], summaries)
        write_rounds(rows, out)
        plots.plot_rounds(rows, out / "plots" / "rounds.png")
        run.log.print(rounds_table(rows, title=f"rounds ({out})"))
    return metrics


def demo(
    out: str | Path = "runs/demo", cfg: RunConfig | None = None, console: Console | None = None, max_plots: int | None = None
) -> RunResult:
    """The whole method on the built-in ``xe75`` simulator: :func:`run_pipeline` on generated references.

    Draws ``DEMO_REFERENCES`` loading cycles (fixed seed), trains on the first ``DEMO_TRAIN`` and tests on the rest;
    the references are saved under ``OUT/refs/{train,test}``.

    Args:
        out: the run folder (resumable).
        cfg: the run's settings; ``config.DEMO`` when None.
        console: where to print (the same text goes to ``OUT/run.log``).
        max_plots: draw the tracking plots of the first ``max_plots`` test references (None: every one).
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

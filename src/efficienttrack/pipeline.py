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
    OUT/metrics.json, OUT/plots/*.png

Held-out figures during training: the PD controller alone is run on the test references first (it is the
baseline, and does not depend on training), and its records are the held-out episodes of both trainings:
the model's 20-step MPE and the policy's model-predicted tracking error on them are logged every
``eval_every`` steps. Training uses all collected episodes, as in the paper; the held-out episodes are
unseen references, under the position controller alone. Each evaluation uses at most
``training.HELD_OUT_STEPS`` recorded steps; with the demo's settings they add 0.7 % to the model's and 2.7 % to
the policy's training time (docs/logged-metrics.md).

A rerun with the same run.json skips every finished stage; an interrupted stage resumes
(collection at its first unwritten pass, training from its checkpoint). A rerun with other
settings into the same folder is refused.
"""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from rich.console import Console

from efficienttrack import dynamics, plots, policy
from efficienttrack.collect import collect
from efficienttrack.config import DEMO, RunConfig
from efficienttrack.cycles import generate_references
from efficienttrack.errors import EfficientTrackError
from efficienttrack.fileio import write_json
from efficienttrack.metrics import compute_metrics, metrics_table, rounded
from efficienttrack.nets import resolve_device
from efficienttrack.records import EpisodeRecord, load_named_records, save_records
from efficienttrack.references import Reference, save_references
from efficienttrack.runtime import track
from efficienttrack.systems.protocol import BatchedSystem
from efficienttrack.systems.spec import SystemSpec
from efficienttrack.training import read_scalars

PLOTTED_REFERENCES = 3
"""Test references drawn in the tracking plots."""
LOGS = "logs"
"""Folder of the training logs in ``OUT``: ``logs/model``, ``logs/policy``."""
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
)
"""What :func:`run_pipeline` writes in its folder (see the module docstring): a fresh start deletes these."""
DEMO_OUTPUTS = (*RUN_OUTPUTS, "refs")
"""What :func:`demo` writes in its folder: the run's outputs and the generated references."""
EVALUATE_OUTPUTS = ("records", "metrics.json", "plots")
"""What :func:`evaluate` writes in its folder: a fresh evaluation deletes these."""


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


class _Stages:
    """Finished-stage markers in ``OUT/stages``: a stage is done when its marker exists."""

    def __init__(self, out: Path) -> None:
        self.folder = out / "stages"
        self.skipped: list[str] = []

    def done(self, name: str) -> dict[str, Any] | None:
        """The facts of finished stage ``name`` (noted as skipped), or None when it has not finished."""
        path = self.folder / f"{name}.json"
        if not path.exists():
            return None
        self.skipped.append(name)
        return json.loads(path.read_text())

    def finish(self, name: str, facts: dict[str, Any]) -> dict[str, Any]:
        """Mark stage ``name`` finished with its ``facts`` (JSON-serializable); returns the facts."""
        write_json(self.folder / f"{name}.json", facts)
        return facts


def _check_run(out: Path, identity: dict[str, Any]) -> None:
    path = out / "run.json"
    if path.exists():
        if json.loads(path.read_text()) != identity:
            raise EfficientTrackError(
                f"{path}: this folder holds a run with other settings, system or references; "
                "use another --out, or --force to start afresh"
            )
    else:
        write_json(path, identity)


def _evaluate(
    stages: _Stages, name: str, out: Path, system: BatchedSystem, pi: torch.nn.Module | None, refs: Sequence[Reference], device
) -> list[EpisodeRecord]:
    folder = out / "records" / name
    if stages.done(f"evaluate_{name}") is not None:
        return load_named_records(folder, [ref.name for ref in refs])
    records = track(system, pi, refs, device=device, description=f"evaluating {name}")
    save_records(records, folder)
    stages.finish(f"evaluate_{name}", {"episodes": len(records), "fallbacks": sum(r.meta["fallbacks"] for r in records)})
    return records


def run_pipeline(
    system: SystemSpec,
    train_refs: Sequence[Reference],
    test_refs: Sequence[Reference],
    out: str | Path,
    cfg: RunConfig,
    console: Console | None = None,
) -> RunResult:
    """The whole method on one system: Algorithm 1, model and policy training, Algorithm 2 vs PD.

    Args:
        system: how to build the closed-loop system (any ``module:callable``, no tuning needed).
        train_refs: references for data collection and training.
        test_refs: held-out references for evaluation.
        out: output folder (see the module docstring); a rerun resumes here.
        cfg: the run's settings.
        console: where to print progress notes and the table (a fresh rich console when None).

    Returns:
        The folder, the metrics written to ``OUT/metrics.json`` and the skipped stages.

    Raises:
        EfficientTrackError: bad system spec, no references, or ``out`` holding another run.
    """
    console = console or Console()
    if not train_refs or not test_refs:
        raise EfficientTrackError("run: needs at least one training and one test reference")
    out = Path(out)
    env = system.open()
    identity = {
        "config": cfg.to_dict(),
        "system": system.to_dict(),
        "train_references": {ref.name: len(ref.q) for ref in train_refs},
        "test_references": {ref.name: len(ref.q) for ref in test_refs},
    }
    _check_run(out, identity)
    cfg.save(out / "config.json")
    stages = _Stages(out)
    device = resolve_device(cfg.device)

    # Algorithm 1: collection (resumes pass by pass)
    collected = collect(env, train_refs, cfg.collect, out / "records" / "train")
    facts = stages.done("collect") or stages.finish("collect", {"interaction_steps": collected.interaction_steps})
    console.print(f"collected {len(collected.records)} episodes, {facts['interaction_steps']} interaction steps")

    # the PD controller alone on the test references: the baseline, and the held-out episodes of both trainings
    pd_records = _evaluate(stages, "pd", out, env, None, test_refs, device)

    # closed-loop dynamics model g_θ
    model_facts = stages.done("model")
    if model_facts is None:
        trained = dynamics.train_model(
            cfg.model,
            collected.records,
            device=device,
            seed=cfg.seed,
            checkpoint=out / "checkpoints" / "model.ckpt",
            log_dir=out / LOGS / "model",
            held_out=pd_records,
        )
        dynamics.save_model(trained.model, out / "model.pt")
        model_facts = stages.finish("model", {"seconds": trained.seconds, "log": f"{LOGS}/model"})
    g_theta = dynamics.load_model(out / "model.pt").to(device)
    console.print(f"model trained ({model_facts['seconds']:.0f} s{', earlier run' if 'model' in stages.skipped else ''})")

    # adjustment policy π_φ
    policy_facts = stages.done("policy")
    if policy_facts is None:
        trained_pi = policy.train_policy(
            cfg.policy,
            g_theta,
            collected.records,
            device=device,
            seed=cfg.seed,
            checkpoint=out / "checkpoints" / "policy.ckpt",
            log_dir=out / LOGS / "policy",
            held_out=pd_records,
        )
        policy.save_policy(trained_pi.policy, out / "policy.pt")
        policy_facts = stages.finish("policy", {"seconds": trained_pi.seconds, "log": f"{LOGS}/policy"})
    pi_phi = policy.load_policy(out / "policy.pt").to(device)
    console.print(f"policy trained ({policy_facts['seconds']:.0f} s{', earlier run' if 'policy' in stages.skipped else ''})")

    # Algorithm 2 on the held-out references
    et_records = _evaluate(stages, "efficienttrack", out, env, pi_phi, test_refs, device)

    # report
    metrics = {
        "pd": rounded(compute_metrics(pd_records)),
        "efficienttrack": rounded(compute_metrics(et_records)),
        "interaction_steps": facts["interaction_steps"],
        "train_seconds": round(model_facts["seconds"] + policy_facts["seconds"], 2),
        "model": {
            "tr_mpe_deg": round(float(dynamics.model_error(g_theta, collected.records).mpe_deg), 4),
            "te_mpe_deg": round(float(dynamics.model_error(g_theta, et_records).mpe_deg), 4),
        },
        "fallbacks": sum(r.meta["fallbacks"] for r in et_records),
        "system": system.to_dict(),
        "config": cfg.to_dict(),
    }
    write_json(out / "metrics.json", metrics)
    plot_dir = out / "plots"
    for ref, pd_rec, et_rec in list(zip(test_refs, pd_records, et_records, strict=True))[:PLOTTED_REFERENCES]:
        plots.plot_tracking({"PD": pd_rec, "EfficientTrack": et_rec}, plot_dir / f"tracking_{ref.name}.png", title=ref.name)
    plots.plot_tracking_error({"PD": pd_records, "EfficientTrack": et_records}, plot_dir / "tracking_error.png")
    curves = {
        name: plots.TrainingCurves(read_scalars(out / facts["log"]), *labels)
        for name, facts, labels in (
            ("model", model_facts, (dynamics.LOSS_LABEL, dynamics.HELD_OUT_TAG, dynamics.HELD_OUT_LABEL)),
            ("policy", policy_facts, (policy.LOSS_LABEL, policy.HELD_OUT_TAG, policy.HELD_OUT_LABEL)),
        )
    }
    plots.plot_training_curves(curves, plot_dir / "training_curves.png")
    console.print(metrics_table({"PD": metrics["pd"], "EfficientTrack": metrics["efficienttrack"]}, title=f"test ({out})"))
    return RunResult(out=out, metrics=metrics, skipped=tuple(stages.skipped))


def evaluate(
    system: SystemSpec,
    refs: Sequence[Reference],
    out: str | Path,
    policy_path: str | Path | None = None,
    device: str = "auto",
    console: Console | None = None,
) -> dict[str, Any]:
    """Algorithm 2 (or the PD controller alone without a policy) on references; records and metrics to ``out``.

    Args:
        system: how to build the closed-loop system.
        refs: the references to track.
        out: folder for ``records/<reference>.npz`` and ``metrics.json``.
        policy_path: a policy checkpoint (``policy.pt``) or None for the PD controller alone.
        device: torch device for the policy (``auto``, ``cpu``, ``cuda``).
        console: where to print the table.

    Returns:
        The content of ``metrics.json`` ({"method", "metrics", "fallbacks", "system", "policy"}).
    """
    console = console or Console()
    env = system.open()
    pi = None
    if policy_path is not None:
        if not Path(policy_path).is_file():
            raise EfficientTrackError(f"--policy {policy_path}: no such file")
        pi = policy.load_policy(policy_path).to(resolve_device(device))
    records = track(env, pi, refs, description="evaluating")
    save_records(records, Path(out) / "records")
    method = "PD" if pi is None else "EfficientTrack"
    result = {
        "method": method,
        "metrics": rounded(compute_metrics(records)),
        "fallbacks": sum(r.meta["fallbacks"] for r in records),
        "system": system.to_dict(),
        "policy": None if policy_path is None else str(policy_path),
    }
    write_json(Path(out) / "metrics.json", result)
    console.print(metrics_table({method: result["metrics"]}, title=f"evaluation ({out})"))
    return result


def demo(out: str | Path = "runs/demo", cfg: RunConfig | None = None, console: Console | None = None) -> RunResult:
    """The whole method on the built-in ``xe75`` simulator with generated references.

    Draws ``DEMO_REFERENCES`` loading cycles (fixed seed), trains on the first ``DEMO_TRAIN`` and
    tests on the rest; the references are saved under ``OUT/refs/{train,test}``.

    Args:
        out: output folder (resumable like :func:`run_pipeline`).
        cfg: the run's settings; ``config.DEMO`` when None.
        console: where to print.

    Returns:
        The result of :func:`run_pipeline`.
    """
    console = console or Console()
    refs = generate_references(DEMO_REFERENCES, seed=DEMO_SEED)
    train, test = refs[:DEMO_TRAIN], refs[DEMO_TRAIN:]
    save_references(train, Path(out) / "refs" / "train")
    save_references(test, Path(out) / "refs" / "test")
    start = time.perf_counter()
    result = run_pipeline(SystemSpec(), train, test, out, cfg or DEMO, console)
    ratio = result.metrics["efficienttrack"]["mae_deg"] / result.metrics["pd"]["mae_deg"]
    console.print(
        f"EfficientTrack MAE = {ratio:.2f} × PD MAE; wall time {time.perf_counter() - start:.0f} s; outputs in {out}"
    )
    return result

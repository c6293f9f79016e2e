"""Ablations: EfficientTrack's whole pipeline once per variant of one setting × seed, at equal data.

An ablation is a study (one system, one train/test split, the preset's EfficientTrack settings) whose jobs are
variants of one setting: ``noise-ratio`` (the noisy:clean mix of Algorithm 1: the paper's Table II), ``k-smooth``
(the weight of the policy's smoothness term: Table III) and ``history`` (the length of the histories the dynamics
model sees). Every variant collects the same number of passes over the training references (the study's
``run_config.collect.passes``), so that they differ only in the setting ablated, and runs
:func:`~efficienttrack.workflow.pipeline.run_pipeline` once, in ``OUT/jobs/efficienttrack-<variant>-s<seed>/run/``.

A variant's job reports one point: the test metrics of EfficientTrack, the model's multi-step prediction errors
(Tr.MPE on the training episodes, Te.MPE on EfficientTrack's test episodes) and Po.MAE, the policy's tracking error
as its model predicts it (:func:`~efficienttrack.learn.policy.predicted_tracking_error`), on the training episodes (the
paper's: "on the model-predicted positions during training") and on the held-out PD episodes of the test references.
"""

from __future__ import annotations

import json
import re
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from rich.console import Console

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import write_json
from efficienttrack.core.settings import canonical_preset
from efficienttrack.data.records import load_records
from efficienttrack.data.references import Reference
from efficienttrack.learn.dynamics import load_model
from efficienttrack.learn.nets import resolve_device
from efficienttrack.learn.policy import load_policy, predicted_tracking_error
from efficienttrack.learn.training import held_out_subset
from efficienttrack.study.jobs import STUDY_PRESETS, Job, Point, Study, Variant, check_seeds, make_study, point
from efficienttrack.systems.spec import SystemSpec
from efficienttrack.workflow.collect import CollectConfig
from efficienttrack.workflow.config import RunConfig
from efficienttrack.workflow.pipeline import run_pipeline

PO_MAE_STEPS = 16_384
"""Most recorded steps Po.MAE is computed from, per set of episodes (:func:`~efficienttrack.learn.training.held_out_subset`:
evenly spaced whole episodes), bounding its cost on a large collection."""
RUN = "run"
"""The pipeline's run folder inside a variant's job folder."""


@dataclass(frozen=True)
class Ablation:
    """One setting of EfficientTrack varied, with the columns of its table.

    Attributes:
        name: its name on the command line (``efficienttrack ablate <name>``).
        title: the table's title.
        setting: what a value sets, in words (the ``--values`` help and the docs).
        values: the values run when none are given, as the command line writes them.
        variant: ``variant(value_text) -> Variant``; raises EfficientTrackError (naming ``--values``) for a bad value.
        columns: the fields of its table (keys of :data:`efficienttrack.study.ablation_report.FIELDS`), as the paper's.
        paper: variant name → {field: the paper's value}, printed under the table for comparison.
    """

    name: str
    title: str
    setting: str
    values: tuple[str, ...]
    variant: Callable[[str], Variant]
    columns: tuple[str, ...]
    paper: dict[str, dict[str, float]]


def _number(text: str, what: str, low: float) -> float:
    """``text`` as a finite number ≥ ``low``; an error naming ``--values`` otherwise."""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not value >= low or value == float("inf"):
        raise EfficientTrackError(f"--values {text!r}: expected {what}")
    return value


def _short(value: float) -> str:
    """``2.0`` → ``2``, ``0.5`` → ``0.5``."""
    return str(value).removesuffix(".0")


def noise_ratio_variant(text: str) -> Variant:
    """A noisy:clean mix of the collection, e.g. ``9:2``; ``0:1`` is no noise and ``1:0`` only noise.

    Args:
        text: ``noisy:clean`` (two weights ≥ 0, not both 0).

    Returns:
        The variant setting ``collect.noise_ratio``.
    """
    noisy, clean = CollectConfig.parse_noise_ratio(text, "--values")
    if noisy == 0:
        name, label = "no-noise", "no noise"
    elif clean == 0:
        name, label = "only-noise", "only noise"
    else:
        name, label = f"ratio-{_short(noisy)}-{_short(clean)}", f"{_short(noisy)}:{_short(clean)}"
    return Variant(name, label, {"collect": {"noise_ratio": [noisy, clean]}})


def k_smooth_variant(text: str) -> Variant:
    """A weight of the policy's action-smoothness term (the paper: 1).

    Args:
        text: a number ≥ 0.

    Returns:
        The variant setting ``policy.k_smooth``.
    """
    k = _number(text, "k_smooth, a number ≥ 0", 0.0)
    return Variant(f"k_smooth-{_short(k)}", f"k_smooth = {_short(k)}", {"policy": {"k_smooth": k}})


def history_variant(text: str) -> Variant:
    """A history length of the dynamics model (the ``cpu`` preset: 5; the paper: 20).

    Args:
        text: an integer ≥ 1.

    Returns:
        The variant setting ``model.history``.
    """
    if not text.strip().isdigit() or int(text) < 1:
        raise EfficientTrackError(f"--values {text!r}: expected a history length, an integer ≥ 1")
    return Variant(f"history-{int(text)}", f"history {int(text)}", {"model": {"history": int(text)}})


ABLATIONS: dict[str, Ablation] = {
    "noise-ratio": Ablation(
        name="noise-ratio",
        title="Table II: the noisy:clean mix of the collection, at equal data",
        setting="collect.noise_ratio, as noisy:clean (0:1 no noise, 1:0 only noise)",
        values=("0:1", "1:0", "9:1", "9:2", "9:3", "9:4"),
        variant=noise_ratio_variant,
        columns=("tr_mpe_deg", "te_mpe_deg", "mae_deg"),
        paper={
            "no-noise": {"tr_mpe_deg": 0.91, "te_mpe_deg": 1.34, "mae_deg": 1.62},
            "only-noise": {"tr_mpe_deg": 0.95, "te_mpe_deg": 1.09, "mae_deg": 1.76},
            "ratio-9-2": {"tr_mpe_deg": 0.67, "te_mpe_deg": 0.79, "mae_deg": 0.81},
        },
    ),
    "k-smooth": Ablation(
        name="k-smooth",
        title="Table III: the weight k_smooth of the policy's smoothness term",
        setting="policy.k_smooth, a number ≥ 0",
        values=("0", "0.5", "1", "2"),
        variant=k_smooth_variant,
        columns=("po_mae_train_deg", "po_mae_heldout_deg", "smt1_deg", "mae_deg"),
        paper={
            "k_smooth-0": {"po_mae_train_deg": 0.19, "smt1_deg": 0.90, "mae_deg": 0.69},
            "k_smooth-1": {"po_mae_train_deg": 0.27, "smt1_deg": 0.74, "mae_deg": 0.60},
            "k_smooth-2": {"po_mae_train_deg": 0.30, "smt1_deg": 0.74, "mae_deg": 0.63},
        },
    ),
    "history": Ablation(
        name="history",
        title="The history length of the dynamics model",
        setting="model.history, an integer ≥ 1 (the cpu preset: 5; the paper: 20)",
        values=("1", "2", "5", "10", "20"),
        variant=history_variant,
        columns=("tr_mpe_deg", "te_mpe_deg", "mae_deg"),
        paper={},
    ),
}
"""The ablations by name."""
NAME = re.compile(r"[A-Za-z0-9._-]+")
"""What a variant's name may hold (it names a folder)."""


def get_ablation(name: str) -> Ablation:
    """The ablation called ``name``.

    Args:
        name: a key of :data:`ABLATIONS`.

    Returns:
        The ablation.

    Raises:
        EfficientTrackError: an unknown name (listing the known ones).
    """
    if name not in ABLATIONS:
        raise EfficientTrackError(f"ablation '{name}': unknown, choose one of {', '.join(ABLATIONS)}")
    return ABLATIONS[name]


def make_ablation_study(
    system: SystemSpec,
    train: list[Reference] | tuple[Reference, ...],
    test: list[Reference] | tuple[Reference, ...],
    preset: str = "cpu",
    passes: int | None = None,
    run_config: RunConfig | None = None,
) -> Study:
    """The study an ablation's variants share: the preset's EfficientTrack settings with ``passes`` collection passes.

    Its budget is the interaction steps of those passes (Σ (L_i − 1) over the training references × passes), the
    same for every variant. Every training reference is trained on: an ablation reports each variant after its
    passes, with no point to select, so it holds none out for validation.

    Args:
        system: the closed-loop system.
        train: training references, each q (L_i, 4) rad.
        test: held-out references.
        preset: ``tiny`` or ``cpu`` (:data:`~efficienttrack.study.jobs.STUDY_PRESETS`).
        passes: collection passes of every variant (None: the settings' own, e.g. 10 for ``cpu``, 3 for ``tiny``).
        run_config: EfficientTrack's settings (None: the preset's).

    Returns:
        The study.

    Raises:
        EfficientTrackError: an unknown preset, bad passes, no references.
    """
    preset = canonical_preset(preset)
    if preset not in STUDY_PRESETS:
        raise EfficientTrackError(f"--preset '{preset}': unknown, choose one of {', '.join(STUDY_PRESETS)}")
    base = make_study(system, train, test, 1, preset, run_config, validation=0)
    if passes is not None:
        try:
            base = replace(base, run_config=replace(base.run_config, collect=replace(base.run_config.collect, passes=passes)))
        except EfficientTrackError as exc:
            raise EfficientTrackError(f"--passes {passes}: {exc}") from exc
    return replace(base, budget=base.run_config.collect.passes * base.steps_per_pass)


def ablation_jobs(
    ablation: Ablation, study: Study, seeds: Sequence[int] = (0,), values: Sequence[str] | None = None
) -> list[Job]:
    """One EfficientTrack job per variant × seed, in the closed loop.

    Args:
        ablation: the ablation.
        study: its study (:func:`make_ablation_study`).
        seeds: the seeds.
        values: the values of the setting, as the command line writes them (None: the ablation's own).

    Returns:
        The jobs, variant by variant in the order given, then seed.

    Raises:
        EfficientTrackError: a bad value, two values giving the same variant, a variant whose settings are invalid,
            or a bad seed (each naming its option).
    """
    variants = [ablation.variant(text.strip()) for text in (ablation.values if values is None else values)]
    if not variants:
        raise EfficientTrackError("--values: give at least one value")
    names = [v.name for v in variants]
    if len(set(names)) != len(names):
        raise EfficientTrackError(f"--values {','.join(values or ablation.values)}: a variant is given twice")
    for variant in variants:
        if not NAME.fullmatch(variant.name):
            raise EfficientTrackError(f"--values: variant name {variant.name!r} cannot name a folder")
        variant.apply(study.run_config)  # its settings are valid, before any job runs
    seeds = check_seeds(tuple(seeds))
    return [Job("efficienttrack", "closed", seed, study, variant) for variant in variants for seed in seeds]


def policy_mae(folder: Path, device: str) -> dict[str, Any]:
    """Po.MAE of a finished run: the policy's tracking error as its model predicts it, in degrees.

    On the training episodes (the run's collection) and on the held-out PD episodes of the test references, at most
    :data:`PO_MAE_STEPS` recorded steps of each (evenly spaced whole episodes), every recorded step a start of a rollout
    of the policy's horizon through the model.

    Args:
        folder: the run folder (``model.pt``, ``policy.pt``, ``records/train``, ``records/pd``).
        device: where to compute.

    Returns:
        ``{"train_deg", "heldout_deg", "train_windows", "heldout_windows"}``.
    """
    g_theta, pi_phi = load_model(folder / "model.pt", device), load_policy(folder / "policy.pt", device)
    steps = pi_phi.cfg.rollout_length
    result = {}
    for key, records in (("train", folder / "records" / "train"), ("heldout", folder / "records" / "pd")):
        error = predicted_tracking_error(g_theta, held_out_subset(load_records(records, True), PO_MAE_STEPS), pi_phi, steps)
        result[f"{key}_deg"], result[f"{key}_windows"] = round(error.mae_deg, 4), error.windows
    return result


def run_variant(job: Job, folder: Path) -> list[Point]:
    """One variant of an ablation: the whole pipeline with the variant's settings and the job's seed, in ``folder/run``.

    The run folder resumes (:func:`~efficienttrack.workflow.pipeline.run_pipeline`); the point is written to
    ``folder/point.json`` when it is complete and read from there on a rerun.

    Args:
        job: the job (its ``variant`` and ``run_config``).
        folder: the job's folder.

    Returns:
        One point: the test metrics of EfficientTrack at the run's interaction steps, with ``passes``, ``warning``
        (the run's guard warning), ``model`` (``{"tr_mpe_deg", "te_mpe_deg"}``), ``po_mae`` (:func:`policy_mae`) and
        ``variant`` (its name, label and overrides).
    """
    if job.variant is None:
        raise EfficientTrackError(f"job {job.name}: not a variant of an ablation")
    done = folder / "point.json"
    if done.exists():
        return [json.loads(done.read_text())]
    cfg = job.run_config
    start = time.perf_counter()
    result = run_pipeline(
        job.study.system, job.study.train, job.study.test, folder / RUN, cfg, Console(quiet=True), 0, "ablate"
    )
    m = result.metrics
    extra = {"passes": cfg.collect.passes, "warning": m["warning"], "model": m["model"]}
    extra["po_mae"] = policy_mae(folder / RUN, str(resolve_device(cfg.device)))
    p = point(m["interaction_steps"], time.perf_counter() - start, m["efficienttrack"], **extra, variant=job.variant.to_dict())
    write_json(done, p)
    return [p]

"""The methods a study compares, by name, and the jobs they give: each runs one job and returns its curve.

A method is a function ``run(job, folder) -> curve``: it trains with ``job.seed`` in ``job.loop`` within
``job.budget`` interaction steps, writing what it likes under ``folder``, and returns the test metrics of the
held-out references at regular interaction counts, as a list of points::

    {"interaction_steps": int, "wall_seconds": float, "metrics": compute_metrics(...) of the test episodes,
     "validation": compute_metrics(...) of the validation episodes (a study with validation references), ...}

Each point is measured on the study's validation references by the path that measures it on the test references:
the PD controller's and EfficientTrack's runtime (:func:`~efficienttrack.deploy.runtime.track`, through
:func:`~efficienttrack.workflow.evaluation.evaluate` for a trained policy), a baseline's own recorder (its
:class:`~efficienttrack.baselines.curve.TrainingRun` holds them; :class:`~efficienttrack.baselines.curve.CurveRecorder`
measures each point on them right after the test references). The ILC oracle learns on the test references themselves
and has none.

``pd`` (the PD controller alone, one point at 0 interactions), ``efficienttrack`` (the whole pipeline after 1, 2, 5,
10 … collection passes; in the open loop a plant model and a PWM policy, :mod:`efficienttrack.baselines.openloop`),
``efficienttrack-rounds`` (one pass, then rounds on the policy's own deployments, a point after each),
the Stable-Baselines3 baselines ``sac`` and ``ppo`` (:func:`efficienttrack.baselines.sb3.train_baseline`, where
that module can be imported), ``tdmpc`` and ``supertrack`` (:mod:`efficienttrack.baselines.tdmpc`,
:mod:`efficienttrack.baselines.supertrack`), and ``ilc``, the oracle lower bound
(:func:`efficienttrack.baselines.ilc.train_ilc`; it sees the test references).
"""

from __future__ import annotations

import importlib.util
import json
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace
from functools import partial
from pathlib import Path
from typing import Any

from rich.console import Console

from efficienttrack.baselines.curve import training_run
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import write_json
from efficienttrack.core.progress import ProgressDisplay
from efficienttrack.core.settings import merge, parse_override, settings_from_dict
from efficienttrack.data.metrics import compute_metrics, rounded
from efficienttrack.data.references import Reference
from efficienttrack.deploy.runtime import track
from efficienttrack.envs.core import LOOPS
from efficienttrack.study.ablations import run_variant
from efficienttrack.study.jobs import STUDY_PRESETS, Job, Point, Study, check_seeds, point
from efficienttrack.workflow.collect import pass_counts
from efficienttrack.workflow.config import MAX_ROUNDS, RunConfig
from efficienttrack.workflow.evaluation import evaluate
from efficienttrack.workflow.pipeline import run_pipeline
from efficienttrack.workflow.rounds import round_references


@dataclass(frozen=True)
class Method:
    """A method of the study.

    Attributes:
        name: its name on the command line (``--methods``), in job names and in ``study.json``.
        label: its name in the table and the figure.
        run: ``run(job, folder) -> list of points`` (see the module docstring).
        loops: the loops it has (``closed``, ``open``).
        seeded: its outcome depends on the seed (else one job, with the first seed, stands for all).
        requires: modules that must be importable for it to be available.
        check: ``check(study)`` raises an EfficientTrackError (naming the option) when the method cannot run in the
            study, before any job runs; None: it can always run.
        settings: ``settings(preset)``, the settings object of the baselines' preset ``cpu``, ``tiny`` … that
            ``--method-set`` changes, its module imported only when called; None: no settings (``pd``).
        separate_runs: the loops where each point of its curve is a run of its own (EfficientTrack's pass counts), so
            that a point chosen among them cost the steps of them all; elsewhere a curve is one run's checkpoints.
        run_settings: its closed loop trains with the run's settings, which the study's ``--set`` changes.
    """

    name: str
    label: str
    run: Callable[[Job, Path], list[Point]]
    loops: tuple[str, ...]
    seeded: bool = True
    requires: tuple[str, ...] = ()
    check: Callable[[Study], None] | None = None
    settings: Callable[[str], Any] | None = None
    separate_runs: tuple[str, ...] = ()
    run_settings: bool = False

    def available(self) -> bool:
        """Whether every module in ``requires`` can be imported here (checked without importing them)."""
        for module in self.requires:
            try:
                if importlib.util.find_spec(module) is None:
                    return False
            except ImportError:  # a parent package is missing
                return False
        return True


def run_pd(job: Job, folder: Path) -> list[Point]:
    """The PD controller alone on the test references (and the validation references): one point at 0 interaction steps.

    Args:
        job: the job (its study's system, test and validation references).
        folder: the job's folder (nothing is written there but the result).

    Returns:
        One point (its wall time that of the test references).
    """
    study = job.study
    start = time.perf_counter()
    system = study.system.open()
    metrics = rounded(compute_metrics(track(system, None, study.test, progress=False, description="pd")))
    wall = time.perf_counter() - start
    if not study.validation:
        return [point(0, wall, metrics, gradient_samples=0)]
    validation = rounded(compute_metrics(track(system, None, study.validation, progress=False, description="pd")))
    return [point(0, wall, metrics, validation=validation, gradient_samples=0)]


def check_passes(study: Study, method: str = "efficienttrack") -> None:
    """Refuse a budget that allows not even one collection pass over the training references (EfficientTrack's minimum).

    Args:
        study: the study.
        method: ``efficienttrack`` or ``efficienttrack-rounds``, whose budget is checked.

    Raises:
        EfficientTrackError: the budget is smaller than one pass (naming ``--budget`` or ``--method-budget``).
    """
    budget = study.budget_of(method)
    if not pass_counts(budget, study.steps_per_pass):
        option = f"--method-budget {method}=" if method in dict(study.method_budgets) else "--budget "
        raise EfficientTrackError(
            f"{option}{budget}: less than one collection pass over the training references "
            f"({study.steps_per_pass} interaction steps), which EfficientTrack needs"
        )


def run_efficienttrack(job: Job, folder: Path) -> list[Point]:
    """EfficientTrack: the pipeline once per pass count (:func:`~efficienttrack.workflow.collect.pass_counts`), each alone.

    The open loop (a plant model and a PWM policy) is :func:`efficienttrack.baselines.openloop.train_efficienttrack_open`;
    an ablation's job (one variant of the settings, at the study's passes) is
    :func:`efficienttrack.study.ablations.run_variant`.

    ``folder/passes_<p>/`` is a run folder (:func:`~efficienttrack.workflow.pipeline.run_pipeline`, which resumes) with the
    study's ``run_config``, ``job.seed`` as the seed of training and of the collection noise, and ``p`` collection
    passes; with validation references, its policy is then scored on them in ``folder/validation/passes_<p>/``
    (:func:`~efficienttrack.workflow.evaluation.evaluate`, which resumes too). The point is written to
    ``folder/passes_<p>/point.json`` when both are finished, and read from there on a rerun.

    Args:
        job: the job.
        folder: the job's folder.

    Returns:
        One point per pass count: the test metrics of EfficientTrack at the run's interaction steps, with ``passes``,
        ``gradient_samples`` (both trainings' windows), the run's guard ``warning`` (None, or why the figures are mostly
        the PD controller's) and, with validation
        references, ``validation``: the policy's metrics on them. Its wall time is the run's, without the validation.

    Raises:
        EfficientTrackError: the budget allows not even one collection pass.
    """
    study = job.study
    check_passes(study)
    if job.variant is not None:
        return run_variant(job, folder)
    if job.loop == "open":
        from efficienttrack.baselines.openloop import train_efficienttrack_open

        return _baseline(job, folder, train_efficienttrack_open)
    base = job.run_config
    curve = []
    for passes in pass_counts(job.budget, study.steps_per_pass):
        run_folder = folder / f"passes_{passes}"
        cfg = replace(base, collect=replace(base.collect, passes=passes))
        done = run_folder / "point.json"
        curve.append(_pipeline_point(job, folder, run_folder, cfg, done, f"passes_{passes}", 0.0, passes=passes))
    return curve


def run_efficienttrack_rounds(job: Job, folder: Path) -> list[Point]:
    """EfficientTrack in rounds (the ``fastset`` line): one collection pass, then as many rounds as the budget holds.

    Round k ≥ 2 deploys the latest policy once on the training references (or ``round_share`` of them) and trains model
    and policy on, warm (:mod:`efficienttrack.workflow.rounds`). ``folder/run/`` is the one run folder, extended round
    by round (:func:`~efficienttrack.workflow.pipeline.run_pipeline` with ``rounds = k``); round k's point, measured on
    the test and validation references as EfficientTrack's are, is written to ``folder/points/round_<k>.json`` and read
    from there on a rerun. A curve is one run's rounds, so a point chosen on it cost only the steps up to it.

    Args:
        job: the job (closed loop).
        folder: the job's folder.

    Returns:
        One point per round, with ``round``, ``gradient_samples`` (so far), ``warning`` and, with validation references,
        ``validation``; its wall time is the run's up to that round, without the validation.

    Raises:
        EfficientTrackError: the budget allows not even one collection pass.
    """
    study = job.study
    check_passes(study, job.method)
    first = replace(job.run_config, collect=replace(job.run_config.collect, passes=1))
    curve: list[Point] = []
    for k in range(1, rounds_within(study.train, first.round_share, job.budget) + 1):
        wall = curve[-1]["wall_seconds"] if curve else 0.0
        done = folder / "points" / f"round_{k}.json"
        cfg = replace(first, rounds=k)
        curve.append(_pipeline_point(job, folder, folder / "run", cfg, done, f"round_{k}", wall, round=k))
    return curve


def rounds_within(train: Sequence[Reference], share: float, budget: int) -> int:
    """How many rounds fit in ``budget`` interaction steps: one collection pass, then each round's deployment.

    Args:
        train: the training references.
        share: the share of them a later round deploys on (``round_share``).
        budget: interaction steps.

    Returns:
        The rounds (at most :data:`~efficienttrack.workflow.config.MAX_ROUNDS`; 0 when not even the pass fits).
    """
    steps, k = sum(len(ref.q) - 1 for ref in train), 0
    while steps <= budget and k < MAX_ROUNDS:
        k += 1
        steps += sum(len(ref.q) - 1 for ref in round_references(train, k + 1, share))
    return k


def _pipeline_point(
    job: Job, folder: Path, run_folder: Path, cfg: RunConfig, done: Path, name: str, wall_before: float, **facts: Any
) -> Point:
    """One point of EfficientTrack's curve: the run in ``run_folder`` with ``cfg``, and its policy on the validation set.

    Args:
        job: the job.
        folder: the job's folder (the validation scoring goes to ``folder/validation/<name>``).
        run_folder: the run's folder (it resumes, and more rounds extend it).
        cfg: the run's settings.
        done: where the point is written when finished, and read from on a rerun.
        name: the validation scoring's folder under ``<job folder>/validation/``.
        wall_before: wall time spent before this run's call (earlier rounds of the same run).
        **facts: the point's own facts (``passes``, ``round``).

    Returns:
        The point.
    """
    if done.exists():
        return json.loads(done.read_text())
    study, start = job.study, time.perf_counter()
    result = run_pipeline(study.system, study.train, study.test, run_folder, cfg, Console(quiet=True), 0, "study")
    m, wall = result.metrics, wall_before + time.perf_counter() - start
    extra = {}
    if study.validation:
        scored = evaluate(study.system, study.validation, folder / "validation" / name, m["policy"], cfg.device,
                          Console(quiet=True), 0)  # fmt: skip
        extra["validation"] = scored["efficienttrack"]
    extra["gradient_samples"] = m.get("gradient_samples")
    p = point(m["interaction_steps"], wall, m["efficienttrack"], **facts, warning=m["warning"], **extra)
    write_json(done, p)
    return p


def _baseline(job: Job, folder: Path, train: Callable[..., list[Point]], validate: bool = True) -> list[Point]:
    """Run a baseline's ``train(run, preset=..., progress=...)`` on the job's run.

    The run (:func:`~efficienttrack.baselines.curve.training_run`) is the job's loop, budget and seed on the study's
    system and references; with the study's validation references (and ``validate``) every point is measured on them
    too, and found so (:func:`require_validation`).

    Args:
        job: the job.
        folder: the job's folder (the baseline's ``curve.json`` goes there).
        train: the baseline's ``train_*`` (imported by the caller: a job imports only what it runs), with the method
            bound for a function that trains several (the SB3 baselines).
        validate: measure the points on the validation references (False: the ILC oracle, which has no policy).

    Returns:
        The baseline's curve.

    Raises:
        EfficientTrackError: a point that should have been measured on the validation references was not.
    """
    study = job.study
    validation = study.validation if validate else ()
    run = training_run(
        job.loop, study.system, study.train, study.test, job.budget, job.seed, folder, validation_refs=validation
    )
    with ProgressDisplay() as progress:  # plain lines in the job's log
        curve = train(run, preset=job_settings(job), progress=progress)
    return require_validation(curve, job.method) if validation else curve


def preset_settings(method: str, preset: str) -> Any:
    """The settings object of a method's preset (:attr:`Method.settings`).

    Args:
        method: a method with settings (:func:`settable`).
        preset: the baselines' preset name (``cpu``, ``tiny``).

    Returns:
        The method's settings dataclass (``OpenLoopSettings`` for ``efficienttrack``, ``SACSettings`` …).
    """
    make = METHODS[method].settings
    assert make is not None, f"{method} has no settings"
    return make(preset)


def changed_settings(method: str, preset: str, changes: Sequence[str]) -> Any:
    """A method's preset with ``--method-set`` changes laid over it, each checked as a settings file's field is.

    Args:
        method: a method with settings (:func:`settable`).
        preset: the baselines' preset name.
        changes: ``method.field=value`` texts (a dotted field reaches into a section: ``supertrack.policy.lr=1e-5``).

    Returns:
        The changed settings.

    Raises:
        EfficientTrackError: a malformed change, an unknown field or a value its field refuses (naming the change).
    """
    settings = preset_settings(method, preset)
    for text in changes:  # one at a time: an error names the change that caused it
        data = merge(asdict(settings), parse_override(text, "--method-set")[method])
        settings = settings_from_dict(type(settings), data, f"--method-set {text}")
    return settings


def job_settings(job: Job) -> Any:
    """What a baseline job trains with: the study preset's name, or its settings with the job's ``--method-set`` changes.

    Args:
        job: the job.

    Returns:
        The preset's name (no change: the job's ``curve.json`` is as before changes existed) or a settings object.
    """
    preset = STUDY_PRESETS[job.study.preset].baselines
    return changed_settings(job.method, preset, job.settings_changes) if job.settings_changes else preset


def check_method_settings(study: Study, jobs: Sequence[Job]) -> None:
    """Refuse ``--method-set`` changes that no job would use, or that do not make valid settings, before any job runs.

    Args:
        study: the study.
        jobs: its jobs.

    Raises:
        EfficientTrackError: a change of an unknown method, of one without settings (``pd``), of EfficientTrack without
            an open-loop job (its closed loop takes ``--set``), or one its settings refuse.
    """
    for method in dict.fromkeys(name for name, _ in study.method_settings):
        changes = study.settings_changes(method)
        if method not in METHODS:
            raise EfficientTrackError(f"--method-set {changes[0]}: unknown method, choose from {', '.join(settable())}")
        if method not in settable():
            runs = " (it runs the closed loop's settings: --set, e.g. --set round_share=0.5)"
            raise EfficientTrackError(f"--method-set {changes[0]}: {method} has no settings to change"
                                      + (runs if METHODS[method].run_settings else ""))  # fmt: skip
        if method == "efficienttrack" and not any(job.settings_changes for job in jobs if job.method == method):
            raise EfficientTrackError(
                f"--method-set {changes[0]}: changes open-loop EfficientTrack, and no job runs it; the closed loop's "
                "settings take --set (e.g. --set policy.k_smooth=0.1)"
            )
        if METHODS[method].available():
            changed_settings(method, STUDY_PRESETS[study.preset].baselines, changes)


def require_validation(curve: list[Point], method: str) -> list[Point]:
    """The curve, once every point is found measured on the validation references.

    Args:
        curve: a method's points.
        method: its name, for the error.

    Returns:
        ``curve``.

    Raises:
        EfficientTrackError: a point has no ``"validation"`` metrics (saying how many).
    """
    missing = sum("validation" not in p for p in curve)
    if missing:
        raise EfficientTrackError(
            f"{method}: {missing} of its {len(curve)} curve points were not measured on the validation references"
        )
    return curve


def run_sb3(job: Job, folder: Path) -> list[Point]:
    """A Stable-Baselines3 baseline (``sac`` or ``ppo``): :func:`efficienttrack.baselines.sb3.train_baseline`.

    Args:
        job: the job (``job.method`` is the algorithm).
        folder: the job's folder (the baseline's ``curve.json`` and ``model.zip`` go there).

    Returns:
        The baseline's curve: its deterministic policy on the test references at its evaluation interaction counts.
    """
    from efficienttrack.baselines.sb3 import train_baseline

    return _baseline(job, folder, partial(train_baseline, job.method))


def run_supertrack(job: Job, folder: Path) -> list[Point]:
    """SuperTrack (:func:`efficienttrack.baselines.supertrack.train_supertrack`), closed or open loop.

    A world model and a policy trained through it, alternating with collection by the policy.

    Args:
        job: the job.
        folder: the job's folder (its ``curve.json`` goes there).

    Returns:
        Its curve on the test references.
    """
    from efficienttrack.baselines.supertrack import train_supertrack

    return _baseline(job, folder, train_supertrack)


def run_tdmpc(job: Job, folder: Path) -> list[Point]:
    """TD-MPC (:func:`efficienttrack.baselines.tdmpc.train_tdmpc`), closed or open loop.

    A study runs its ``cpu`` preset, TD-MPC (reduced), or ``tiny``, never the paper's settings (a GPU job): its label
    says so.

    Args:
        job: the job.
        folder: the job's folder (its ``curve.json`` and ``model.pt`` go there).

    Returns:
        Its curve on the test references.
    """
    from efficienttrack.baselines.tdmpc import train_tdmpc

    return _baseline(job, folder, train_tdmpc)


def check_trial(study: Study) -> None:
    """Refuse a budget smaller than one ILC trial (every test reference once).

    Args:
        study: the study.

    Raises:
        EfficientTrackError: the ILC budget is smaller than one trial (naming the option).
    """
    from efficienttrack.baselines.ilc import trial_steps

    budget, steps = study.budget_of("ilc"), trial_steps(study.test)
    if budget < steps:
        option = "--method-budget ilc=" if "ilc" in dict(study.method_budgets) else "--budget "
        raise EfficientTrackError(f"{option}{budget}: less than one ILC trial over the test references ({steps} steps)")


def run_ilc(job: Job, folder: Path) -> list[Point]:
    """The ILC oracle (:func:`efficienttrack.baselines.ilc.train_ilc`): trials on the test references themselves.

    It sees the test references, so it is a lower bound on the error a reference adjustment can reach, not a
    competitor; its label says so. Its corrections belong to the test references, so it has no validation points.

    Args:
        job: the job.
        folder: the job's folder (the oracle's ``curve.json`` goes there).

    Returns:
        One point per trial: the test metrics after k trials at k × one trial's interaction steps.
    """
    from efficienttrack.baselines.ilc import train_ilc

    return _baseline(job, folder, train_ilc, validate=False)


SB3_MODULES = ("stable_baselines3", "efficienttrack.baselines.sb3")
"""What the SB3 baselines need."""


def _settings_of(module: str, function: str, *args: str) -> Callable[[str], Any]:
    """``preset → module.function(*args, preset)``, the module imported only when called (a job imports what it runs)."""

    def settings(preset: str) -> Any:
        return getattr(importlib.import_module(module), function)(*args, preset)

    return settings


METHODS: dict[str, Method] = {
    "pd": Method("pd", "PD", run_pd, ("closed",), seeded=False),
    "efficienttrack": Method("efficienttrack", "EfficientTrack", run_efficienttrack, LOOPS, check=check_passes,
                             settings=_settings_of("efficienttrack.baselines.openloop", "open_settings"),
                             separate_runs=("closed",), run_settings=True),
    "efficienttrack-rounds": Method("efficienttrack-rounds", "EfficientTrack (rounds)", run_efficienttrack_rounds,
                                    ("closed",), check=partial(check_passes, method="efficienttrack-rounds"),
                                    run_settings=True),
    "sac": Method("sac", "SAC (reduced)", run_sb3, LOOPS, requires=SB3_MODULES,
                  settings=_settings_of("efficienttrack.baselines.settings", "method_settings", "sac")),
    "ppo": Method("ppo", "PPO", run_sb3, LOOPS, requires=SB3_MODULES,
                  settings=_settings_of("efficienttrack.baselines.settings", "method_settings", "ppo")),
    "tdmpc": Method("tdmpc", "TD-MPC (reduced)", run_tdmpc, LOOPS,
                    settings=_settings_of("efficienttrack.baselines.tdmpc", "tdmpc_settings")),
    "supertrack": Method("supertrack", "SuperTrack (reduced)", run_supertrack, LOOPS,
                         settings=_settings_of("efficienttrack.baselines.supertrack", "supertrack_settings")),
    "ilc": Method("ilc", "ILC (oracle: sees the test references)", run_ilc, ("closed",), seeded=False, check=check_trial,
                  settings=_settings_of("efficienttrack.baselines.ilc", "ilc_settings")),
}  # fmt: skip
"""The methods by name, in the order the reports list them; the one place a method is described."""


def settable() -> list[str]:
    """The methods whose settings ``--method-set`` changes (EfficientTrack's in the open loop; its closed loop: ``--set``)."""
    return [name for name, method in METHODS.items() if method.settings is not None]


def available_methods() -> list[str]:
    """The names of the methods that can run here (their modules import), in registry order."""
    return [name for name, method in METHODS.items() if method.available()]


def make_jobs(
    study: Study, methods: Sequence[str] | None = None, loops: Sequence[str] = ("closed",), seeds: Sequence[int] = (0,)
) -> list[Job]:
    """The jobs of a study: every method × each of its loops among ``loops`` × seeds.

    A method without a loop asked for gets no job in it; an unseeded method (``pd``) gets one job, with the first seed.
    The open loop needs a PWM-level plant (``--plant``, or a built-in system's own).

    Args:
        study: the study.
        methods: method names (None: every available one).
        loops: ``closed`` and/or ``open``.
        seeds: the seeds.

    Returns:
        The jobs, method by method in the order given, then loop, then seed.

    Raises:
        EfficientTrackError: an unknown or unavailable method (also in the study's ``method_budgets``), one that cannot
            run in the study (its ``check``), an unknown loop, a bad seed, the open loop without a plant, no job at
            all (each naming its option), or a ``--method-set`` change :func:`check_method_settings` refuses.
    """
    names = available_methods() if methods is None else list(methods)
    for name in names:
        if name not in METHODS:
            raise EfficientTrackError(f"--methods {name}: unknown method, choose from {', '.join(METHODS)}")
        if not METHODS[name].available():
            raise EfficientTrackError(
                f"--methods {name}: not available here (needs {', '.join(METHODS[name].requires)}); "
                f"available: {', '.join(available_methods())}"
            )
    for name, _ in study.method_budgets:
        if name not in METHODS:
            raise EfficientTrackError(f"--method-budget {name}=…: unknown method, choose from {', '.join(METHODS)}")
    if not names or len(set(names)) != len(names):
        raise EfficientTrackError(f"--methods {','.join(names)}: give each method once, at least one")
    for loop in loops:
        if loop not in LOOPS:
            raise EfficientTrackError(f"--loops {loop}: unknown loop, choose from {', '.join(LOOPS)}")
    for name in names:
        check = METHODS[name].check
        if check is not None:
            check(study)
    seeds = check_seeds(tuple(seeds))
    jobs = [
        Job(name, loop, seed, study)
        for name in names
        for loop in dict.fromkeys(loops)
        if loop in METHODS[name].loops
        for seed in (seeds if METHODS[name].seeded else seeds[:1])
    ]
    if not jobs:
        raise EfficientTrackError(
            f"--methods {','.join(names)} --loops {','.join(loops)}: none of these methods has these loops"
        )
    if any(job.loop == "open" for job in jobs) and study.system.open_plant() is None:
        raise EfficientTrackError(
            f"--loops open: the system {study.system.system_name} has no PWM-level plant under it; name one with --plant"
        )
    check_method_settings(study, jobs)
    return jobs

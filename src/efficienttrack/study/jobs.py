"""What a study is: one system, one train/test split, an interaction budget, and its jobs (method × loop × seed).

A job is one method trained with one seed in one loop (``closed``: the policy adjusts the PD controller's
reference; ``open``: the policy sends PWM), evaluated on the held-out references at regular interaction counts,
giving a curve of test metrics against interaction steps. A study may hold some of its training references out of
every method's training (:func:`split_validation`): each point is then measured on them too, and the report chooses
each curve's point by them, never by the test references. Each job owns the folder ``OUT/jobs/<method>-<loop>-s<seed>/``.
A job of an ablation (:mod:`~efficienttrack.study.ablations`) also carries a :class:`Variant` of EfficientTrack's
settings, and owns ``OUT/jobs/<method>-<variant>-s<seed>/``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from efficienttrack.core.configfile import check_seed
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.settings import canonical_preset
from efficienttrack.data.references import Reference, references_sha256
from efficienttrack.systems.spec import SystemSpec
from efficienttrack.workflow.config import PRESETS, RunConfig, amend

STUDY_CONFIG = "study_config.json"
"""What a study folder is (system, references, budget, preset): a rerun must match it."""
JOBS = "jobs"
"""The folder of the jobs' folders inside a study folder."""
RESULT = "result.json"
"""Written last by a finished job: a rerun skips the job."""
ERROR = "error.json"
"""Written by a failed job (removed when it succeeds on a rerun)."""
Point = dict[str, Any]
"""One point of a method's curve: ``{"interaction_steps", "wall_seconds", "metrics", ...}`` (:func:`point`)."""
VALIDATION_SHARE = 10
"""Unless told, a study holds out one in this many of its training references for validation, rounded down
(:func:`default_validation`)."""
VALIDATION_SEED = 0
"""Seed of the permutation that picks a study's validation references (:func:`split_validation`)."""


@dataclass(frozen=True)
class StudyPreset:
    """The sizes of a study's methods."""

    run: str
    """EfficientTrack's settings: a name of :data:`efficienttrack.workflow.config.PRESETS`."""
    baselines: str
    """The baselines' settings: the name of their presets (``tiny``, ``cpu``) in :mod:`efficienttrack.baselines`."""
    budget: int
    """Interaction steps per job when the study gives none."""
    method_budgets: tuple[tuple[str, int], ...] = ()
    """(method, interaction steps) replacing ``budget`` for that method when the study gives none for it."""


STUDY_PRESETS: dict[str, StudyPreset] = {
    "tiny": StudyPreset(run="tiny", baselines="tiny", budget=20_000, method_budgets=(("tdmpc", 2_000),)),
    "cpu": StudyPreset(run="cpu", baselines="cpu", budget=200_000),
}
"""``tiny``: tiny networks, minutes (the tests; TD-MPC, which updates and plans at every step, gets 2,000 steps);
``cpu``: the ``cpu`` preset, and the baselines' ``cpu`` settings (earlier names ``quick`` and ``full`` are read too)."""


def default_validation(count: int) -> int:
    """How many training references a study holds out for validation unless told (``--validation``).

    A tenth (:data:`VALIDATION_SHARE`), rounded down: 4 of the paper's 40, and none below 10 references, where even
    one held out would take a large share of a small training set (such a study reports no selected point).

    Args:
        count: the training references given.

    Returns:
        The number to hold out.
    """
    return count // VALIDATION_SHARE


def split_validation(
    train: list[Reference] | tuple[Reference, ...], count: int
) -> tuple[tuple[Reference, ...], tuple[Reference, ...]]:
    """Hold ``count`` of the training references out of training, for validation.

    Which ones: the references sorted by name, permuted by a generator seeded with :data:`VALIDATION_SEED`, the first
    ``count``. The choice is fixed per study: the same for every method and every seed (it does not depend on the
    jobs' seeds), and for any order the references are given in. A permutation rather than the last ``count`` by name:
    reference folders are numbered in the order they were recorded or generated, and the last ones may share a session
    or a kind of cycle; drawn over the whole set, the validation references are like the others.

    Args:
        train: the training references given, each q (L_i, 4) rad.
        count: how many to hold out (0: none).

    Returns:
        (the references left for training, the validation references), each in the order given.

    Raises:
        EfficientTrackError: ``count`` is not an integer ≥ 0, or would not leave the methods most of the training
            references (naming ``--validation``).
    """
    if not isinstance(count, int) or isinstance(count, bool) or count < 0:
        raise EfficientTrackError(f"--validation {count!r}: expected a number of training references ≥ 0")
    if count and 2 * count >= len(train):
        raise EfficientTrackError(
            f"--validation {count}: would hold out {count} of the {len(train)} training references; hold out fewer than "
            f"half (at most {max(len(train) - 1, 0) // 2} here) so that the methods train on most of them, or 0 for none"
        )
    by_name = sorted(range(len(train)), key=lambda i: train[i].name)
    held = {by_name[i] for i in np.random.default_rng(VALIDATION_SEED).permutation(len(train))[:count]}
    return (tuple(ref for i, ref in enumerate(train) if i not in held), tuple(ref for i, ref in enumerate(train) if i in held))


@dataclass(frozen=True, eq=False)
class Study:
    """One system, one train/test split, an interaction budget per job, and the settings of the methods.

    Attributes:
        system: the closed-loop system (and the plant under it, for the open loop).
        train: the references the methods train on, each q (L_i, 4) rad (the validation references are not among them).
        test: the held-out references the methods are scored on.
        budget: interaction steps each job may spend (training interactions with the system).
        preset: a name of :data:`STUDY_PRESETS`.
        run_config: EfficientTrack's settings (the preset's ``run`` preset; its seed and passes are set per job).
        method_budgets: (method, interaction steps) pairs that replace ``budget`` for those methods' jobs (a costly
            baseline stopped earlier, a sample-hungry one given more).
        validation: training references held out of every method's training (:func:`split_validation`); each curve
            point is measured on them too, and the report chooses each curve's point by them. Empty: no validation.
        method_settings: (method, ``method.field=value``) pairs, in the order given (``--method-set``): changes to a
            method's settings over the preset's (a baseline's, or open-loop EfficientTrack's), checked by
            :func:`~efficienttrack.study.methods.make_jobs`.
    """

    system: SystemSpec
    train: tuple[Reference, ...]
    test: tuple[Reference, ...]
    budget: int
    preset: str
    run_config: RunConfig
    method_budgets: tuple[tuple[str, int], ...] = ()
    validation: tuple[Reference, ...] = ()
    method_settings: tuple[tuple[str, str], ...] = ()

    def __post_init__(self) -> None:
        """Check the references, the budgets and the preset (EfficientTrackError naming the option)."""
        if not self.train or not self.test:
            raise EfficientTrackError("study: needs at least one training (--train-refs) and one test reference (--test-refs)")
        if not isinstance(self.budget, int) or isinstance(self.budget, bool) or self.budget < 1:
            raise EfficientTrackError(f"--budget {self.budget!r}: expected a number of interaction steps ≥ 1")
        for method, steps in self.method_budgets:
            if not isinstance(steps, int) or isinstance(steps, bool) or steps < 1:
                raise EfficientTrackError(f"--method-budget {method}={steps!r}: expected a number of interaction steps ≥ 1")
        names = [method for method, _ in self.method_budgets]
        if len(set(names)) != len(names):
            raise EfficientTrackError(f"--method-budget: a method is given twice ({', '.join(names)})")
        if self.preset not in STUDY_PRESETS:
            raise EfficientTrackError(f"--preset '{self.preset}': unknown, choose one of {', '.join(STUDY_PRESETS)}")

    def settings_changes(self, method: str) -> tuple[str, ...]:
        """The ``--method-set`` changes of ``method``, in order, each as given (``supertrack.policy.lr=1e-5``).

        Args:
            method: a method name.
        """
        return tuple(text for name, text in self.method_settings if name == method)

    def budget_of(self, method: str) -> int:
        """Interaction steps a job of ``method`` may spend: its ``method_budgets`` entry, else ``budget``.

        Args:
            method: a method name.

        Returns:
            The budget.
        """
        return dict(self.method_budgets).get(method, self.budget)

    @property
    def steps_per_pass(self) -> int:
        """Interaction steps of one collection pass over the training references: Σ (L_i − 1)."""
        return sum(ref.steps for ref in self.train)

    def identity(self) -> dict[str, Any]:
        """What the study is, as ``study_config.json`` records it (a rerun into the same folder must match).

        Methods, loops and seeds are not part of it: a rerun may add jobs to a study. A study without validation has
        no ``validation`` fields, as before the setting existed: a folder made then resumes with none (``--validation
        0``), and one made with another count is refused, the refusal naming ``validation``.

        Returns:
            ``{"system", "validation": count held out, "validation_references": {name: length} (these two only with a
            validation split), "train_references": {name: length} of every training reference given, the validation
            ones included, "test_references": {name: length}, "references_sha256", "budget", "method_budgets":
            {method: steps}, "preset", "run_config", "method_settings": {method: [change]} (only with changes)}``.
        """
        validation = {"validation": len(self.validation), "validation_references": {r.name: len(r) for r in self.validation}}
        return {
            "system": self.system.to_dict(),
            **(validation if self.validation else {}),
            "train_references": {ref.name: len(ref) for ref in (*self.train, *self.validation)},
            "test_references": {ref.name: len(ref) for ref in self.test},
            "references_sha256": references_sha256((*self.train, *self.validation, *self.test)),
            "budget": self.budget,
            "method_budgets": dict(self.method_budgets),
            "preset": self.preset,
            "run_config": self.run_config.to_dict(),
            **({"method_settings": self._changes_by_method()} if self.method_settings else {}),
        }

    def _changes_by_method(self) -> dict[str, list[str]]:
        """``{method: [change, ...]}`` of :attr:`method_settings`."""
        changes: dict[str, list[str]] = {}
        for method, text in self.method_settings:
            changes.setdefault(method, []).append(text)
        return changes


def make_study(
    system: SystemSpec,
    train: list[Reference] | tuple[Reference, ...],
    test: list[Reference] | tuple[Reference, ...],
    budget: int | None = None,
    preset: str = "cpu",
    run_config: RunConfig | None = None,
    method_budgets: dict[str, int] | None = None,
    validation: int | None = None,
    method_settings: Sequence[str] = (),
) -> Study:
    """A study with the preset's defaults filled in, and ``validation`` of the training references held out.

    Args:
        system: the closed-loop system.
        train: training references, each q (L_i, 4) rad (the validation references are taken from them).
        test: held-out references.
        budget: interaction steps per job (None: the preset's).
        preset: ``tiny`` or ``cpu`` (:data:`STUDY_PRESETS`; ``quick``, ``full``: their earlier names).
        run_config: EfficientTrack's settings (None: the preset's ``run`` preset).
        method_budgets: method name → interaction steps for that method's jobs instead of ``budget`` (added to, and
            overriding, the preset's own).
        validation: training references to hold out for validation (:func:`split_validation`; 0: none; None:
            :func:`default_validation`, a tenth of them).
        method_settings: ``method.field=value`` changes to a method's settings (``--method-set``), in order.

    Returns:
        The study.

    Raises:
        EfficientTrackError: an unknown preset, a budget < 1, no references, a bad ``validation`` count, a change that
            does not start with a method's name.
    """
    preset = canonical_preset(preset)
    if preset not in STUDY_PRESETS:
        raise EfficientTrackError(f"--preset '{preset}': unknown, choose one of {', '.join(STUDY_PRESETS)}")
    sizes = STUDY_PRESETS[preset]
    kept, held = split_validation(tuple(train), default_validation(len(train)) if validation is None else validation)
    return Study(
        system=system,
        train=kept,
        test=tuple(test),
        budget=sizes.budget if budget is None else budget,
        preset=preset,
        run_config=PRESETS[sizes.run] if run_config is None else run_config,
        method_budgets=tuple(sorted({**dict(sizes.method_budgets), **(method_budgets or {})}.items())),
        validation=held,
        method_settings=tuple((_changed_method(text), text) for text in method_settings),
    )


def _changed_method(text: str) -> str:
    """The method a ``--method-set`` change names: what comes before its first dot."""
    method, dot, rest = text.partition(".")
    if not dot or not method.strip() or "=" not in rest or "=" in method:
        raise EfficientTrackError(f"--method-set '{text}': expected METHOD.field=value, e.g. supertrack.policy.lr=1e-5")
    return method.strip()


@dataclass(frozen=True, eq=False)
class Variant:
    """EfficientTrack's settings changed in one way: a variant of an ablation.

    Attributes:
        name: its name in job folders (letters, digits, ``.``, ``_``, ``-``), e.g. ``ratio-9-2``.
        label: its name in the table and the figure, e.g. ``9:2``.
        overrides: the RunConfig fields it sets, as a plain mapping in :meth:`RunConfig.to_dict`'s form, e.g.
            ``{"collect": {"noise_ratio": [9, 2]}}`` (a section's fields not named keep the study's).
    """

    name: str
    label: str
    overrides: Mapping[str, Any]

    def apply(self, cfg: RunConfig) -> RunConfig:
        """``cfg`` with the overrides, checked field by field.

        Args:
            cfg: the study's settings.

        Returns:
            The variant's settings.

        Raises:
            EfficientTrackError: an override names an unknown field or gives a bad value (naming the variant).
        """
        return amend(cfg, dict(self.overrides), f"variant {self.name}")

    def to_dict(self) -> dict[str, Any]:
        """``{"name", "label", "overrides"}`` (JSON-serializable)."""
        return {"name": self.name, "label": self.label, "overrides": dict(self.overrides)}


@dataclass(frozen=True, eq=False)
class Job:
    """One method, one loop, one seed of a study (and, in an ablation, one variant of EfficientTrack's settings).

    Attributes:
        method: a name of :data:`efficienttrack.study.methods.METHODS`.
        loop: ``closed`` or ``open``.
        seed: the seed of everything random in the job (training, collection noise).
        study: the study it belongs to.
        variant: None, or the variant of the study's EfficientTrack settings the job runs (an ablation's job).
    """

    method: str
    loop: str
    seed: int
    study: Study
    variant: Variant | None = None

    @property
    def budget(self) -> int:
        """Interaction steps this job may spend (:meth:`Study.budget_of` its method)."""
        return self.study.budget_of(self.method)

    @property
    def name(self) -> str:
        """``<method>-<loop>-s<seed>``, or ``<method>-<variant>-s<seed>`` for a variant: the job's folder name."""
        return f"{self.method}-{self.loop if self.variant is None else self.variant.name}-s{self.seed}"

    @property
    def settings_changes(self) -> tuple[str, ...]:
        """The study's ``--method-set`` changes this job trains with (closed-loop EfficientTrack has none: ``--set``)."""
        if self.method == "efficienttrack" and self.loop != "open":
            return ()
        return self.study.settings_changes(self.method)

    @property
    def run_config(self) -> RunConfig:
        """EfficientTrack's settings for this job: the study's, the variant's overrides, ``seed`` as every seed."""
        cfg = self.study.run_config if self.variant is None else self.variant.apply(self.study.run_config)
        return replace(cfg, seed=self.seed)  # collect.seed follows


def job_folder(out: str | Path, name: str) -> Path:
    """The folder of job ``name`` in study folder ``out``.

    Args:
        out: the study folder.
        name: the job's name (:attr:`Job.name`).

    Returns:
        ``out/jobs/<name>``.
    """
    return Path(out) / JOBS / name


def check_seeds(seeds: list[int] | tuple[int, ...]) -> tuple[int, ...]:
    """The seeds, checked: integers ≥ 0, at least one, no repeats.

    Args:
        seeds: the seeds given.

    Returns:
        The seeds as a tuple, in the order given.

    Raises:
        EfficientTrackError: no seed, a repeated one, or one that is not an integer in [0, 2^63 − 1] (naming ``--seeds``).
    """
    if not seeds:
        raise EfficientTrackError("--seeds: give at least one seed")
    for seed in seeds:
        check_seed(seed, "--seeds")
    if len(set(seeds)) != len(seeds):
        raise EfficientTrackError(f"--seeds {','.join(map(str, seeds))}: a seed is repeated")
    return tuple(seeds)


def point(interaction_steps: int, wall_seconds: float, metrics: dict[str, Any], **extra: Any) -> Point:
    """A point of a curve.

    Args:
        interaction_steps: training interactions with the system so far.
        wall_seconds: wall time the method took to get there.
        metrics: :func:`~efficienttrack.data.metrics.compute_metrics` of the test episodes.
        **extra: further facts of the point (e.g. ``passes``).

    Returns:
        ``{"interaction_steps", "wall_seconds", "metrics", **extra}``.
    """
    return {"interaction_steps": int(interaction_steps), "wall_seconds": round(float(wall_seconds), 2), "metrics": metrics,
            **extra}  # fmt: skip

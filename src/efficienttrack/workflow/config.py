"""The settings of a whole run (collection, model, policy, seed, device) as one tree, and its named presets.

``RunConfig`` composes the component configs: :class:`~efficienttrack.workflow.collect.CollectConfig`,
``ModelConfig`` (``efficienttrack.learn.dynamics``) and ``PolicyConfig`` (``efficienttrack.learn.policy``). Every
field states its bounds (:mod:`efficienttrack.core.settings`), checked the same way in Python, from a file and from
``--set section.field=value``. ``RunConfig()`` is the ``cpu`` preset.
Presets: ``paper`` (the paper's settings), ``cpu`` (a laptop-sized run), ``fastset`` (the paper's fastset: one
collection pass, then three rounds, at the ``cpu`` sizes), ``tiny`` (seconds; tests).
Configs are read from YAML (a safe loader that also reads ``1e-5`` as a number) or JSON; unknown or mistyped fields
are errors naming the file and the field.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import yaml

from efficienttrack.core.configfile import MAX_SEED, read_mapping_file
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import atomic_write, write_json
from efficienttrack.core.settings import DEVICE, check_fields, merge, parse_override, plain_form, setting, settings_from_dict
from efficienttrack.learn.settings import MODEL_PRESETS, POLICY_PRESETS, ModelConfig, PolicyConfig
from efficienttrack.workflow.collect import CollectConfig

MAX_ROUNDS = 100
"""Most continual-learning rounds a run may ask for (the paper: 3)."""
ROUND_DATA = ("all", "new")
"""What a later round may train on: every episode so far, or only its own deployment pass."""
"""Torch devices a run may name: ``auto`` takes CUDA when present."""


@dataclass(frozen=True)
class RunConfig:
    """Everything that decides the outcome of ``efficienttrack run``: the settings tree (``efficienttrack config show``)."""

    collect: CollectConfig = setting(default_factory=CollectConfig)
    """Algorithm 1: noise level, noisy:clean mix, passes."""
    model: ModelConfig = setting(default_factory=ModelConfig)
    """Closed-loop dynamics model g_θ and its training."""
    policy: PolicyConfig = setting(default_factory=PolicyConfig)
    """Adjustment policy π_φ and its training."""
    seed: int = setting(0, ge=0, le=MAX_SEED)
    """The run's one seed: of the collection noise (``collect.seed`` follows it), of model and policy training."""
    device: str = setting("auto", pattern=DEVICE)
    """Torch device: ``auto`` (CUDA when available), ``cpu`` or ``cuda``."""
    rounds: int = setting(1, ge=1, le=MAX_ROUNDS)
    """Continual-learning rounds: round 1 is Algorithm 1; each later round deploys the previous policy on the
    training references (one pass, no noise) and trains model and policy on, starting from the previous ones."""
    round_data: str = setting("all", choices=ROUND_DATA)
    """What a later round trains on: ``all`` (every episode recorded so far) or ``new`` (its own deployment
    pass only, as the paper does)."""
    round_share: float = setting(1.0, gt=0, le=1, before=1.0)
    """Share of the training references a later round deploys on (at least one; 1: all, the paper's rounds): a window
    that moves on round by round, so that each reference comes in turn. Smaller rounds are more rounds within the same
    interaction steps, each deploying the latest policy (SuperTrack collects about 4,096 steps between trainings)."""
    warm_budget: float = setting(0.5, gt=0)
    """Optimizer steps (or epochs) of a later round's trainings, as a share of round 1's: they start from the
    previous round's networks and need fewer."""
    round_warmup: float = setting(0.1, ge=0, le=0.5, before=0.0)
    """Share of a later round's optimizer steps over which each training's learning rate rises linearly to its value
    (it replaces ``warmup`` of both sections in rounds k ≥ 2, round 1 keeps theirs; 0: from the first step, as folders
    made before 2026-11-29 resume). A warm start's fresh Adam steps otherwise throw the trained networks off (one
    paper-simulator seed diverged); 0.1 lowered round 4's validation MAE in eight runs of nine on three plants and the
    fastset's Round 3 on three seeds (docs/comparison.md)."""
    time_budget: float | None = setting(None, gt=0, before=None)
    """Minutes of wall time for the whole run, all rounds (``--time-budget``): every training's optimizer steps are
    scaled down by one factor, from step times measured on this machine when training starts, or, when the minutes
    leave room, the model's up to 3 times, then the policy's up to 1.5 times (:mod:`efficienttrack.workflow.time_budget`);
    None: the configured steps."""

    def __post_init__(self) -> None:
        """Check the fields (EfficientTrackError naming the field); ``collect.seed`` takes the run's seed."""
        check_fields(self)
        if self.collect.seed != self.seed:
            object.__setattr__(self, "collect", replace(self.collect, seed=self.seed))

    def to_dict(self) -> dict[str, Any]:
        """JSON/YAML-serializable form (:func:`~efficienttrack.core.settings.plain_form`: fields added later only when set)."""
        return plain_form(self)

    def save(self, path: str | Path) -> Path:
        """Write the config atomically, as YAML or JSON, every field.

        The file reads back as these settings (:func:`load_config`) whatever the defaults are when it is read.

        Args:
            path: destination; ``.yaml``/``.yml`` gives YAML, anything else JSON.

        Returns:
            The path written.
        """
        path = Path(path)
        data = plain_form(self, every_field=True)
        if path.suffix in (".yaml", ".yml"):
            return atomic_write(path, lambda f: yaml.safe_dump(data, f, sort_keys=False), mode="w")
        return write_json(path, data)


PRESETS: dict[str, RunConfig] = {
    "paper": RunConfig(
        collect=CollectConfig(sigma_max=0.05, noise_ratio=(9, 2), noise_rho=0.0, passes=10),
        model=MODEL_PRESETS["paper"],
        policy=POLICY_PRESETS["paper"],
    ),
    "cpu": RunConfig(),
    "fastset": RunConfig(
        collect=CollectConfig(passes=1),
        model=MODEL_PRESETS["cpu"],
        policy=POLICY_PRESETS["cpu"],
        rounds=3,
    ),
    "tiny": RunConfig(
        collect=CollectConfig(passes=3),
        model=MODEL_PRESETS["tiny"],
        policy=POLICY_PRESETS["tiny"],
    ),
}


DEMO = PRESETS["cpu"]
"""Settings of ``efficienttrack demo`` on the built-in ``xe75`` (≈ 10 min on 2 CPU cores): the ``cpu`` preset."""


def preset(name: str) -> RunConfig:
    """The named preset; EfficientTrackError for other names.

    Args:
        name: ``paper``, ``cpu``, ``fastset`` or ``tiny``.

    Returns:
        The preset's RunConfig.
    """
    if name not in PRESETS:
        raise EfficientTrackError(f"--preset '{name}': unknown, choose one of {', '.join(PRESETS)}")
    return PRESETS[name]


def from_dict(data: Any, source: str = "config", stored: bool = False) -> RunConfig:
    """Build a RunConfig from a plain mapping (:meth:`RunConfig.to_dict`'s form), every field checked.

    Args:
        data: ``{"collect": {...}, "model": {...}, "policy": {...}, "seed": int, "device": str, "rounds": int,
            "round_data": str, "warm_budget": float, "time_budget": float or None}``; missing fields keep their
            defaults (the ``cpu`` preset). ``collect.seed``, when given, must equal ``seed``: it follows it.
        source: how to name the data in errors (the file, the override).
        stored: ``data`` is a :meth:`RunConfig.to_dict` the package wrote: a field added later that it lacks takes
            its ``before`` value (:func:`~efficienttrack.core.settings.settings_from_dict`), not today's default.

    Returns:
        The config.

    Raises:
        EfficientTrackError: an unknown field, a wrong type or a value out of its bounds (naming ``source`` and the
            field), or a ``collect.seed`` other than ``seed``.
    """
    cfg = settings_from_dict(RunConfig, data, source, stored=stored)
    given = data.get("collect", {}).get("seed", cfg.seed) if isinstance(data.get("collect"), dict) else cfg.seed
    if given != cfg.seed:
        raise EfficientTrackError(
            f"{source}: collect.seed is {given} but seed is {cfg.seed}: the collection noise follows the run's seed, "
            "set seed alone"
        )
    return cfg


def amend(cfg: RunConfig, changes: dict[str, Any], source: str) -> RunConfig:
    """``cfg`` with the fields in ``changes`` replaced (a section's fields not named keep ``cfg``'s), checked.

    Args:
        cfg: the settings to start from.
        changes: a nested mapping in :meth:`RunConfig.to_dict`'s form, e.g. ``{"model": {"history": 5}}``; a
            ``provenance`` entry (a run's ``config.json`` has one) is ignored.
        source: where the changes come from, named in errors.

    Returns:
        The new settings.
    """
    base = cfg.to_dict()
    del base["collect"]["seed"]  # derived from seed: a change of seed alone must carry it along
    changes = {name: value for name, value in changes.items() if name != "provenance"}
    return from_dict(merge(base, changes), source, stored=True)  # to_dict leaves out a field at its ``before`` value


def load_config(path: str | Path, base: RunConfig | None = None) -> RunConfig:
    """Read a RunConfig from YAML or ``.json`` (:func:`~efficienttrack.core.configfile.read_mapping_file`), field by field.

    Args:
        path: the file; component sections (``collect``, ``model``, ``policy``) may list only some fields. A file
            with a ``provenance`` entry is a run's ``config.json``: the whole tree as the package wrote it, read as
            that run's settings (a field added since, which it lacks, takes what the code did then, not ``base``).
        base: where fields not given come from (the ``cpu`` preset when None).

    Returns:
        The config.

    Raises:
        EfficientTrackError: unreadable file, unknown field, wrong type or invalid value (naming the field).
    """
    path = Path(path)
    data = read_mapping_file(path)
    if not isinstance(data, dict):
        raise EfficientTrackError(f"{path}: expected a mapping of fields")
    if "provenance" in data:
        return from_dict({name: value for name, value in data.items() if name != "provenance"}, str(path), stored=True)
    return amend(base or PRESETS["cpu"], data, str(path))


def apply_overrides(cfg: RunConfig, overrides: Sequence[str] | None) -> RunConfig:
    """``cfg`` with ``--set section.field=value`` overrides applied in order, each checked as a file's field is.

    Args:
        cfg: the settings.
        overrides: e.g. ``["model.history=5", "seed=3", "collect.noise_ratio=[9, 2]"]``; values are read as YAML.

    Returns:
        The new settings.

    Raises:
        EfficientTrackError: a malformed override, an unknown field or a refused value (naming the override).
    """
    for text in overrides or ():
        cfg = amend(cfg, parse_override(text), f"--set {text}")
    return cfg


def resolve_settings(
    preset_name: str = "cpu", config: str | Path | None = None, overrides: Sequence[str] | None = None
) -> RunConfig:
    """The settings a command runs with: the preset, amended by the ``--config`` file, then by ``--set`` overrides.

    Args:
        preset_name: a name of :data:`PRESETS`.
        config: a YAML/JSON file of fields to change, or None.
        overrides: ``section.field=value`` strings, applied last.

    Returns:
        The settings.
    """
    cfg = preset(preset_name)
    if config is not None:
        cfg = load_config(config, cfg)
    return apply_overrides(cfg, overrides)

"""The settings of a whole run (collection, model, policy, seed, device) and its named presets.

``RunConfig`` composes the component configs: :class:`~efficienttrack.workflow.collect.CollectConfig`,
``ModelConfig`` (``efficienttrack.learn.dynamics``) and ``PolicyConfig`` (``efficienttrack.learn.policy``).
Presets: ``paper`` (the paper's settings), ``cpu`` (a laptop-sized run), ``fastset`` (the paper's fastset: one
collection pass, then three rounds, at the ``cpu`` sizes), ``tiny`` (seconds; tests).
Configs are read from YAML (a safe loader that also reads ``1e-5`` as a number) or JSON and checked field by field against
the dataclass types; unknown or mistyped fields are errors naming the file and the field.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import yaml

from efficienttrack.core.configfile import check_seed, config_from_dict, read_mapping_file
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import atomic_write, write_json
from efficienttrack.learn.dynamics import MODEL_PRESETS, ModelConfig
from efficienttrack.learn.policy import POLICY_PRESETS, PolicyConfig
from efficienttrack.workflow.collect import CollectConfig

MAX_ROUNDS = 100
"""Most continual-learning rounds a run may ask for (the paper: 3)."""
ROUND_DATA = ("all", "new")
"""What a later round may train on: every episode so far, or only its own deployment pass."""


@dataclass(frozen=True)
class RunConfig:
    """Everything that decides the outcome of ``efficienttrack run``."""

    collect: CollectConfig = field(default_factory=CollectConfig)
    """Algorithm 1: noise level, noisy:clean mix, passes."""
    model: ModelConfig = field(default_factory=ModelConfig)
    """Closed-loop dynamics model g_θ and its training."""
    policy: PolicyConfig = field(default_factory=PolicyConfig)
    """Adjustment policy π_φ and its training."""
    seed: int = 0
    """Seed of model and policy training."""
    device: str = "auto"
    """Torch device: ``auto`` (CUDA when available), ``cpu`` or ``cuda``."""
    rounds: int = 1
    """Continual-learning rounds: round 1 is Algorithm 1; each later round deploys the previous policy on the
    training references (one pass, no noise) and trains model and policy on, starting from the previous ones."""
    round_data: str = "all"
    """What a later round trains on: ``all`` (every episode recorded so far) or ``new`` (its own deployment
    pass only, as the paper does)."""
    warm_budget: float = 0.5
    """Optimizer steps (or epochs) of a later round's trainings, as a share of round 1's: they start from the
    previous round's networks and need fewer."""
    time_budget: float | None = None
    """Minutes of wall time for the whole run, all rounds (``--time-budget``): every training's optimizer steps are
    scaled down by one factor, from step times measured on this machine when training starts
    (:mod:`efficienttrack.workflow.time_budget`); None: the configured steps."""

    def __post_init__(self) -> None:
        """Validate the run-level fields (EfficientTrackError naming the field)."""
        check_seed(self.seed, "RunConfig.seed")
        if not isinstance(self.rounds, int) or isinstance(self.rounds, bool) or not 1 <= self.rounds <= MAX_ROUNDS:
            raise EfficientTrackError(f"RunConfig.rounds must be an integer ≥ 1 and ≤ {MAX_ROUNDS}, got {self.rounds!r}")
        if self.round_data not in ROUND_DATA:
            raise EfficientTrackError(f"RunConfig.round_data must be one of {', '.join(ROUND_DATA)}, got {self.round_data!r}")
        for name in ("warm_budget", "time_budget"):
            budget = getattr(self, name)
            if name == "time_budget" and budget is None:
                continue
            if not isinstance(budget, (int, float)) or isinstance(budget, bool) or not (math.isfinite(budget) and budget > 0):
                raise EfficientTrackError(f"RunConfig.{name} must be a number > 0, got {budget!r}")

    def to_dict(self) -> dict[str, Any]:
        """JSON/YAML-serializable form (tuples become lists); ``time_budget`` only when set.

        Without a budget the form is the one from before the field existed, so that run, study and ablation folders
        made then still match their settings and resume.
        """
        data = json.loads(json.dumps(asdict(self)))
        if data["time_budget"] is None:
            del data["time_budget"]
        return data

    def save(self, path: str | Path) -> Path:
        """Write the config atomically, as YAML or JSON.

        Args:
            path: destination; ``.yaml``/``.yml`` gives YAML, anything else JSON.

        Returns:
            The path written.
        """
        path = Path(path)
        if path.suffix in (".yaml", ".yml"):
            return atomic_write(path, lambda f: yaml.safe_dump(self.to_dict(), f, sort_keys=False), mode="w")
        return write_json(path, self.to_dict())


PRESETS: dict[str, RunConfig] = {
    "paper": RunConfig(
        collect=CollectConfig(sigma_max=0.05, noise_ratio=(9, 2), passes=10),
        model=MODEL_PRESETS["paper"],
        policy=POLICY_PRESETS["paper"],
    ),
    "cpu": RunConfig(
        collect=CollectConfig(),
        model=MODEL_PRESETS["cpu"],
        policy=POLICY_PRESETS["cpu"],
    ),
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
"""Settings of ``efficienttrack demo`` on the built-in ``xe75`` (≈ 7 min on 2 CPU cores): the ``cpu`` preset."""


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


def from_dict(data: Any, source: str = "config") -> RunConfig:
    """Build a RunConfig from a plain mapping, every component validated field by field.

    Args:
        data: ``{"collect": {...}, "model": {...}, "policy": {...}, "seed": int, "device": str, "rounds": int,
            "round_data": str, "warm_budget": float, "time_budget": float or None}``; missing fields keep their defaults.
        source: how to name the data in errors (the file).

    Returns:
        The config.
    """
    if not isinstance(data, dict):
        raise EfficientTrackError(f"{source}: expected a mapping of fields, got {type(data).__name__}")
    known = {f.name for f in dataclasses.fields(RunConfig)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise EfficientTrackError(f"{source}: unknown field(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}")
    values: dict[str, Any] = {}
    for name, cls in (("collect", CollectConfig), ("model", ModelConfig), ("policy", PolicyConfig)):
        if name in data:
            values[name] = config_from_dict(cls, data[name], f"{source}: {name}")
    if "seed" in data:
        if not isinstance(data["seed"], int) or isinstance(data["seed"], bool):
            raise EfficientTrackError(f"{source}: field 'seed' must be an integer, got {data['seed']!r}")
        values["seed"] = data["seed"]
    if "device" in data:
        if data["device"] not in ("auto", "cpu", "cuda"):
            raise EfficientTrackError(f"{source}: field 'device' must be auto, cpu or cuda, got {data['device']!r}")
        values["device"] = data["device"]
    for name in ("rounds", "round_data", "warm_budget", "time_budget"):
        if name in data:
            values[name] = data[name]
    try:
        return RunConfig(**values)
    except EfficientTrackError as exc:
        raise EfficientTrackError(f"{source}: {exc}") from exc


def load_config(path: str | Path, base: RunConfig | None = None) -> RunConfig:
    """Read a RunConfig from YAML or ``.json`` (:func:`~efficienttrack.core.configfile.read_mapping_file`), field by field.

    Args:
        path: the file; component sections (``collect``, ``model``, ``policy``) may list only some fields; a
            ``provenance`` entry (a run's ``config.json`` has one) is ignored.
        base: where fields not given come from (the ``cpu`` preset when None).

    Returns:
        The config.

    Raises:
        EfficientTrackError: unreadable file, unknown field, wrong type or invalid value (naming the field).
    """
    path = Path(path)
    data = read_mapping_file(path)
    base = base or PRESETS["cpu"]
    if not isinstance(data, dict):
        raise EfficientTrackError(f"{path}: expected a mapping of fields")
    merged = base.to_dict()
    for name, value in data.items():
        if name == "provenance":  # a run's config.json records where it came from: a fact, not a setting
            continue
        if isinstance(value, dict) and isinstance(merged.get(name), dict):
            merged[name] = {**merged[name], **value}
        else:
            merged[name] = value
    return from_dict(merged, str(path))


def with_overrides(
    cfg: RunConfig,
    seed: int | None = None,
    device: str | None = None,
    rounds: int | None = None,
    round_data: str | None = None,
    time_budget: float | None = None,
) -> RunConfig:
    """``cfg`` with the command-line overrides applied.

    Args:
        cfg: the config.
        seed: new seed of training and of collection noise, or None to keep.
        device: new device, or None to keep.
        rounds: new number of rounds, or None to keep.
        round_data: what later rounds train on (``all`` or ``new``), or None to keep.
        time_budget: minutes for the whole run, or None to keep.

    Returns:
        The new config.
    """
    changes: dict[str, Any] = {}
    if seed is not None:
        changes["seed"] = seed
        changes["collect"] = replace(cfg.collect, seed=seed)
    if device is not None:
        changes["device"] = device
    if rounds is not None:
        changes["rounds"] = rounds
    if round_data is not None:
        changes["round_data"] = round_data
    if time_budget is not None:
        changes["time_budget"] = time_budget
    return replace(cfg, **changes)

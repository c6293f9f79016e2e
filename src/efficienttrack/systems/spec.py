"""Systems by name: built-in names and ``module.path:callable`` specs, and the one place a plant is closed with a PD law.

A **spec** is a built-in name (``xe75``: the calibrated hydraulic simulator under the real PD law; ``paper``: the
paper's own simulator under its PD law, :mod:`efficienttrack.systems.paper`; ``learned``: a trained closed-loop
model, :mod:`efficienttrack.learn.learned_system`) or an import path ``"module.path:callable"``. The callable is called
with the keyword options (``--system-opt key=value``) and must return the system. Modules are looked up in the
current working directory first, so a ``mymachines.py`` next to where the command runs is found without installing it.

:class:`SystemSpec` is what the CLI and the pipeline carry around: a reference-level system (``--system``), or a
PWM-level plant (``--plant``) closed with PD gains (``--pd``, by default a built-in plant's own); with neither, the
built-in ``xe75``. A limits file (``--limits``) amends the limits the runtime guard enforces
(:mod:`efficienttrack.systems.limits`).
"""

from __future__ import annotations

import importlib
import os
import sys
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.systems.limits import GuardLimits
from efficienttrack.systems.pd import PD_PRESETS, ClosedLoop, PDGains
from efficienttrack.systems.protocol import BatchedSystem

DEFAULT_SYSTEM = "xe75"
"""The system used when neither ``--system`` nor ``--plant`` is given."""
BUILTIN_SYSTEMS: dict[str, str] = {
    "xe75": "efficienttrack.systems.hydraulic:xe75_closed_loop",
    "paper": "efficienttrack.systems.paper:paper_closed_loop",
    "learned": "efficienttrack.learn.learned_system:learned_system",
}
"""Built-in reference-level systems: name → import path."""
BUILTIN_PLANTS: dict[str, str] = {
    "xe75": "efficienttrack.systems.hydraulic:xe75_plant",
    "paper": "efficienttrack.systems.paper:paper_plant",
}
"""Built-in PWM-level plants: name → import path."""


@contextmanager
def _working_directory_first() -> Iterator[None]:
    """Put the current working directory at the front of ``sys.path`` while importing a user's module.

    The ``efficienttrack`` console script does not have the working directory on its path (``python -m``
    and the interactive interpreter do), so without this a ``mymachines.py`` beside the user is not found.
    """
    cwd = os.getcwd()
    sys.path.insert(0, cwd)
    try:
        yield
    finally:
        sys.path.remove(cwd)


def _resolve(spec: str, builtins: Mapping[str, str], what: str) -> Callable[..., Any]:
    target = builtins.get(spec, spec)
    if ":" not in target:
        names = ", ".join(sorted(builtins)) or "none"
        raise EfficientTrackError(
            f"unknown {what} '{spec}': give a built-in name ({names}) or an import path 'module.path:callable'"
        )
    module_name, _, attr = target.partition(":")
    try:
        with _working_directory_first():
            module = importlib.import_module(module_name)
    except ImportError as exc:
        raise EfficientTrackError(f"{what} '{spec}': cannot import module '{module_name}': {exc}") from exc
    factory = getattr(module, attr, None)
    if factory is None or not callable(factory):
        raise EfficientTrackError(f"{what} '{spec}': module '{module_name}' has no callable '{attr}'")
    return factory


def load_callable(spec: str, what: str) -> Callable[..., Any]:
    """The callable an import path ``"module.path:callable"`` names (a user's machine adapter, ``deploy --machine``).

    Args:
        spec: the import path; modules are looked up in the current working directory first.
        what: what it is, for errors (e.g. ``"machine"``).

    Returns:
        The callable.
    """
    return _resolve(spec, {}, what)


def _build(spec: str, builtins: Mapping[str, str], what: str, options: Mapping[str, Any]) -> BatchedSystem:
    factory = _resolve(spec, builtins, what)
    try:
        system = factory(**options)
    except EfficientTrackError:
        raise
    except TypeError as exc:
        raise EfficientTrackError(f"{what} '{spec}': cannot be built with options {dict(options)}: {exc}") from exc
    except Exception as exc:  # a user's adapter that cannot open its machine, a bad option value
        raise EfficientTrackError(f"{what} '{spec}': building it failed: {type(exc).__name__}: {exc}") from exc
    return BatchedSystem(system, name=f"{what} '{spec}'")


def load_system(spec: str, **options: Any) -> BatchedSystem:
    """Load a reference-level ClosedLoopSystem.

    Args:
        spec: a built-in name (``xe75``, ``paper``, ``learned``) or ``"module.path:callable"``.
        **options: keyword options passed to the callable (``--system-opt key=value`` on the CLI).

    Returns:
        The system, wrapped in a checked batched view.
    """
    return _build(spec, BUILTIN_SYSTEMS, "system", options)


def load_plant(spec: str, **options: Any) -> BatchedSystem:
    """Load a PWM-level Plant (same spec rules as :func:`load_system`).

    Args:
        spec: a built-in name (``xe75``, ``paper``) or ``"module.path:callable"``.
        **options: keyword options passed to the callable (``--system-opt key=value`` on the CLI).

    Returns:
        The plant, wrapped in a checked batched view.
    """
    return _build(spec, BUILTIN_PLANTS, "plant", options)


def close_loop(plant: BatchedSystem, gains: PDGains, name: str) -> BatchedSystem:
    """A plant under PD position control, as a checked reference-level system: the one place this is wired.

    Args:
        plant: the checked view of a PWM-level plant (from :func:`load_plant`).
        gains: the PD law.
        name: how to name the closed loop in errors.

    Returns:
        The checked, batched view of ``ClosedLoop(plant, gains)``.
    """
    return BatchedSystem(ClosedLoop(plant.system, gains), name=name)


@dataclass(frozen=True)
class SystemSpec:
    """How to build the closed-loop system: a reference-level system, or a plant under PD control (``xe75`` without either)."""

    system: str | None = None
    """Built-in name or ``module:callable`` of a ClosedLoopSystem (``--system``)."""
    plant: str | None = None
    """Built-in name or ``module:callable`` of a Plant wrapped with the PD controller (``--plant``)."""
    pd: str | None = None
    """PD gains for ``plant``: a preset name or a JSON file (``--pd``); None: :attr:`pd_name`."""
    options: tuple[tuple[str, Any], ...] = ()
    """Keyword options of the callable (``--system-opt key=value``)."""
    limits: str | None = None
    """YAML/JSON file of the guard's limits, or a shipped preset's name (``xe75``) (``--limits``); fields it leaves out keep
    the system's own (:meth:`GuardLimits.load`)."""

    def __post_init__(self) -> None:
        """Refuse a spec naming both a system and a plant."""
        if self.system is not None and self.plant is not None:
            raise EfficientTrackError("give --system SPEC or --plant SPEC, not both")

    @property
    def system_name(self) -> str:
        """The reference-level system built when no plant is given: ``system``, or :data:`DEFAULT_SYSTEM`."""
        return self.system if self.system is not None else DEFAULT_SYSTEM

    @property
    def pd_name(self) -> str:
        """The PD gains of the plant: ``pd``, else a built-in plant's own preset (``paper``), else ``xe75``.

        For a built-in system without ``--plant`` (``--system paper``) it names the PD law of the system's own plant.
        """
        if self.pd is not None:
            return self.pd
        name = self.plant if self.plant is not None else self.system_name
        return name if name in PD_PRESETS and name in BUILTIN_PLANTS else "xe75"

    def to_dict(self) -> dict[str, Any]:
        """JSON form (for run.json and metrics.json); ``limits`` only when a file is given (older run.json match)."""
        return {
            "system": None if self.plant else self.system_name,
            "plant": self.plant,
            "pd": self.pd_name if self.plant else None,
            "options": dict(self.options),
            **({"limits": self.limits} if self.limits is not None else {}),
        }

    def open(self) -> BatchedSystem:
        """Build the closed-loop system this spec names.

        Returns:
            The checked, batched view of the system (a plant is closed with its PD gains), its ``limits`` amended
            by the limits file.
        """
        options = dict(self.options)
        if self.plant is None:
            system = load_system(self.system_name, **options)
        else:
            plant = load_plant(self.plant, **options)
            pd = self.pd_name
            system = close_loop(plant, PDGains.load(pd), name=f"plant '{self.plant}' under PD '{pd}'")
        if self.limits is not None:
            system.limits = GuardLimits.load(self.limits, base=system.limits)
        return system

    def open_plant(self) -> BatchedSystem | None:
        """The PWM-level plant under the system, where there is one: ``--plant``, or a built-in system's own plant.

        Returns:
            The checked view of the plant, or None for a reference-level system without one (a user's machine,
            a learned model).
        """
        options = dict(self.options)
        if self.plant is not None:
            return load_plant(self.plant, **options)
        if self.system_name in BUILTIN_PLANTS:
            return load_plant(self.system_name, **options)
        return None

"""EfficientTrack: high-precision excavator trajectory tracking from learned closed-loop dynamics.

The Python API is as short as the command line: ``efficienttrack.run``, ``collect``, ``train_model``,
``train_policy``, ``evaluate``, ``round``, ``export``, ``load_policy`` and ``run_study`` (the ``study`` command; the
name ``efficienttrack.study`` is its package), with what they take (``SystemSpec``, ``preset``, references and
records). They are imported on first use, so ``import efficienttrack`` stays light: the torch-free runtime imports
the package without torch.

The Gymnasium environments ``EfficientTrack/ClosedLoop-v0`` and ``EfficientTrack/OpenLoop-v0`` are registered when
Gymnasium is imported, before or after this package, which imports none itself (Gymnasium 1.x has no plugin entry
point: :class:`_RegisterWithGymnasium` does it). ``import efficienttrack.envs`` registers them too.
"""

import importlib.abc
import importlib.util
import inspect
import sys
from importlib import import_module
from types import ModuleType
from typing import Any

from efficienttrack.core.errors import missing_extra

__version__ = "0.1.0"

API: dict[str, tuple[str, str]] = {
    "run": ("efficienttrack.workflow.pipeline", "run_pipeline"),
    "evaluate": ("efficienttrack.workflow.evaluation", "evaluate"),
    "demo": ("efficienttrack.workflow.pipeline", "demo"),
    "collect": ("efficienttrack.workflow.collect", "collect"),
    "train_model": ("efficienttrack.learn.dynamics", "train_model"),
    "train_policy": ("efficienttrack.learn.policy", "train_policy"),
    "round": ("efficienttrack.workflow.next_round", "next_round"),
    "export": ("efficienttrack.deploy.export", "export_policy"),
    "load_policy": ("efficienttrack.learn.policy", "load_policy"),
    "load_model": ("efficienttrack.learn.dynamics", "load_model"),
    "run_study": ("efficienttrack.study.run", "run_study"),
    "SystemSpec": ("efficienttrack.systems.spec", "SystemSpec"),
    "load_system": ("efficienttrack.systems.spec", "load_system"),
    "load_plant": ("efficienttrack.systems.spec", "load_plant"),
    "RunConfig": ("efficienttrack.workflow.config", "RunConfig"),
    "preset": ("efficienttrack.workflow.config", "preset"),
    "Reference": ("efficienttrack.data.references", "Reference"),
    "load_references": ("efficienttrack.data.references", "load_references"),
    "generate_references": ("efficienttrack.data.cycles", "generate_references"),
    "load_records": ("efficienttrack.data.records", "load_records"),
    "compute_metrics": ("efficienttrack.data.metrics", "compute_metrics"),
}
"""The top-level names: name → (module, attribute), imported when first used."""

__all__ = ["__version__", *API]


def __getattr__(name: str) -> Any:
    """Import a top-level API name from its module on first use (PEP 562)."""
    if name not in API:
        raise AttributeError(f"module 'efficienttrack' has no attribute '{name}'")
    module, attribute = API[name]
    try:
        value = getattr(import_module(module), attribute)
    except ModuleNotFoundError as exc:  # on the core install: name the extra that installs the library
        missing = missing_extra(exc, f"efficienttrack.{name}")
        if missing is None:
            raise
        raise missing from exc
    if inspect.isfunction(value):  # a wrong argument is one EfficientTrackError naming it (core/api_check.py)
        from efficienttrack.core.api_check import checked

        value = checked(name, value)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    """The module's names, the lazily imported API included."""
    return sorted({*globals(), *API})


class _RegisterWithGymnasium(importlib.abc.MetaPathFinder):
    """Registers the environments the moment Gymnasium's own import finishes (then leaves ``sys.meta_path``)."""

    def find_spec(self, name: str, path: Any, target: Any = None) -> Any:
        """Gymnasium's spec, its loader made to register the environments after it runs; None for any other module."""
        if name != "gymnasium":
            return None
        sys.meta_path.remove(self)
        spec = importlib.util.find_spec(name)
        if spec is not None and spec.loader is not None:
            load = spec.loader.exec_module

            def load_and_register(module: ModuleType) -> None:
                load(module)
                import_module("efficienttrack.envs")  # registers on import

            spec.loader.exec_module = load_and_register  # type: ignore[method-assign]
        return spec


def _gymnasium_installed() -> bool:
    """Whether Gymnasium can be imported here, found without importing it."""
    try:
        return importlib.util.find_spec("gymnasium") is not None
    except ImportError:  # an import hook that refuses it, as on an install without it
        return False


if sys.modules.get("gymnasium") is not None:
    import_module("efficienttrack.envs")
elif _gymnasium_installed():
    sys.meta_path.insert(0, _RegisterWithGymnasium())

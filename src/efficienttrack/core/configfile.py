"""Frozen config dataclasses from JSON/YAML files and mappings, validated field by field (no code execution)."""

from __future__ import annotations

import dataclasses
import json
import math
import re
import types
from pathlib import Path
from typing import Any, TypeVar, Union, get_args, get_origin, get_type_hints

import yaml

from efficienttrack.core.errors import EfficientTrackError

ConfigT = TypeVar("ConfigT")


class ConfigLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that reads ``1e-5``, ``3E4`` and ``.5`` as floats (YAML 1.2), where YAML 1.1 gives strings.

    PyYAML follows YAML 1.1, whose float pattern needs a dot and a signed exponent (``1.0e-5``); a
    learning rate written ``lr: 1e-5`` would otherwise be refused as a string.
    """


ConfigLoader.yaml_implicit_resolvers = {key: list(value) for key, value in yaml.SafeLoader.yaml_implicit_resolvers.items()}
ConfigLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(
        r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
        |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
        |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
        |[-+]?[0-9][0-9_]*(?::[0-5]?[0-9])+\.[0-9_]*
        |[-+]?\.(?:inf|Inf|INF)
        |\.(?:nan|NaN|NAN))$""",
        re.X,
    ),
    list("-+0123456789."),
)


def read_mapping_file(path: str | Path) -> Any:
    """Read a config file: JSON when it ends in ``.json``, else YAML through :class:`ConfigLoader` (no code execution).

    Args:
        path: the file.

    Returns:
        The loaded data (a mapping for a well-formed config; the caller checks).

    Raises:
        EfficientTrackError: the file is missing, unreadable or not valid JSON/YAML.
    """
    path = Path(path)
    try:
        text = path.read_text()
        return json.loads(text) if path.suffix == ".json" else yaml.load(text, Loader=ConfigLoader)
    except OSError as exc:
        raise EfficientTrackError(f"{path}: cannot read the config ({exc.strerror or exc})") from exc
    except UnicodeDecodeError as exc:
        raise EfficientTrackError(f"{path}: cannot read the config (not a text file: {exc.reason})") from exc
    except json.JSONDecodeError as exc:
        raise EfficientTrackError(f"{path}: cannot read the config (not valid JSON: {exc})") from exc
    except yaml.YAMLError as exc:
        raise EfficientTrackError(f"{path}: cannot read the config (not valid YAML: {yaml_problem(exc)})") from exc


def yaml_problem(exc: yaml.YAMLError) -> str:
    """PyYAML's error on one line: the problem and where (its own message spans several lines, with a caret).

    Args:
        exc: the error ``yaml.load`` raised.

    Returns:
        E.g. ``"expected ',' or ']', but got ':' (line 2, column 2)"``.
    """
    problem = getattr(exc, "problem", None)
    mark = getattr(exc, "problem_mark", None)
    if problem is None:
        return " ".join(str(exc).split())
    return f"{problem} (line {mark.line + 1}, column {mark.column + 1})" if mark is not None else problem


MAX_SEED = 2**63 - 1
"""Largest seed: what both numpy's and torch's generators accept (neither takes a negative one)."""


def check_seed(seed: object, source: str) -> int:
    """``seed`` when it is an integer in ``[0, MAX_SEED]``; else an EfficientTrackError naming ``source``.

    Args:
        seed: the candidate seed.
        source: the field or option it comes from, for the message.

    Returns:
        The seed.
    """
    if not isinstance(seed, int) or isinstance(seed, bool) or not 0 <= seed <= MAX_SEED:
        raise EfficientTrackError(f"{source}: a seed must be an integer in [0, 2^63 − 1], got {seed!r}")
    return seed


def config_from_dict(cls: type[ConfigT], data: dict[str, Any], source: str) -> ConfigT:
    """Build the frozen config dataclass ``cls`` from JSON/YAML ``data``, validating names and types field by field.

    Args:
        cls: the config class (a dataclass whose fields have int, float, bool, str, tuple or ``X | None`` types).
        data: the loaded mapping; missing fields keep their defaults.
        source: the file or option the data came from, for messages.

    Returns:
        The config.
    """
    if not isinstance(data, dict):
        raise EfficientTrackError(f"{source}: expected a mapping of {cls.__name__} fields, got {type(data).__name__}")
    hints = get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(data) - names)
    if unknown:
        raise EfficientTrackError(
            f"{source}: unknown {cls.__name__} field(s) {', '.join(unknown)}; known: {', '.join(sorted(names))}"
        )
    values = {name: _coerce(hints[name], value, f"{source}: field '{name}'") for name, value in data.items()}
    try:
        return cls(**values)
    except (TypeError, ValueError, EfficientTrackError) as exc:  # the class's own checks name the field; add the file
        raise EfficientTrackError(f"{source}: {exc}") from exc


def _coerce(hint: Any, value: Any, where: str) -> Any:
    """Check ``value`` against the type ``hint`` (int, float, bool, str, tuple[float, ...], X | None) and convert."""
    origin = get_origin(hint)
    if origin in (Union, types.UnionType):
        options = get_args(hint)
        if value is None and type(None) in options:
            return None
        (inner,) = [option for option in options if option is not type(None)]
        return _coerce(inner, value, where)
    if origin is tuple:
        if not isinstance(value, list | tuple) or not all(map(is_finite_number, value)):
            raise EfficientTrackError(f"{where} must be a list of finite numbers, got {value!r}")
        return tuple(float(v) for v in value)
    if hint is bool:
        if not isinstance(value, bool):
            raise EfficientTrackError(f"{where} must be true or false, got {value!r}")
        return value
    if hint is int:
        if not isinstance(value, int) or isinstance(value, bool):
            raise EfficientTrackError(f"{where} must be an integer, got {value!r}")
        return value
    if hint is float:
        if not is_finite_number(value):
            raise EfficientTrackError(f"{where} must be a finite number, got {value!r}")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise EfficientTrackError(f"{where} must be a string, got {value!r}")
        return value
    raise EfficientTrackError(f"{where}: unsupported config type {hint}")


def is_finite_number(value: Any) -> bool:
    """True when ``value`` is an int or float that is finite as a float (not a bool, NaN, ±inf or a huge int)."""
    if not isinstance(value, int | float) or isinstance(value, bool):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:
        return False

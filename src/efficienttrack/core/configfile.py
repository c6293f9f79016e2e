"""Config files read without code execution (YAML through a safe loader, or JSON), and the checks of single values."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any

import yaml

from efficienttrack.core.errors import EfficientTrackError

MAX_CONFIG_BYTES = 1 << 20
"""Largest config, limits, gains or preset file read (1 MiB; the largest shipped is a few kB), checked before parsing."""


class DuplicateKey(yaml.YAMLError):
    """A mapping gives one key twice: YAML and JSON keep the last, which would silently replace the first."""


class ConfigLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that reads ``1e-5`` as a float and refuses a mapping that gives one key twice.

    ``3E4`` and ``.5`` are floats too (YAML 1.2), where YAML 1.1 gives strings: PyYAML follows YAML 1.1, whose float
    pattern needs a dot and a signed exponent (``1.0e-5``); a learning rate written ``lr: 1e-5`` would otherwise be
    refused as a string. YAML and JSON keep the last of two equal keys, which would silently replace the first.
    """

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        """The mapping, refusing a key given twice (:class:`DuplicateKey`, naming the key and its second line).

        Args:
            node: the YAML mapping node.
            deep: construct nested objects at once (PyYAML's own argument).
        """
        seen: set[Any] = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            if isinstance(key, list | dict):
                continue  # unhashable: PyYAML's own constructor refuses it with its message
            if key in seen:
                raise DuplicateKey(f"the key {key!r} is given twice (line {key_node.start_mark.line + 1})")
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


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
        size = path.stat().st_size
        if size > MAX_CONFIG_BYTES:
            raise EfficientTrackError(
                f"{path}: cannot read the config ({size:,} bytes, more than the {MAX_CONFIG_BYTES:,} a config may have)"
            )
        text = path.read_text()
    except OSError as exc:
        raise EfficientTrackError(f"{path}: cannot read the config ({exc.strerror or exc})") from exc
    except UnicodeDecodeError as exc:
        raise EfficientTrackError(f"{path}: cannot read the config (not a text file: {exc.reason})") from exc
    if path.suffix == ".json":
        try:
            return json.loads(text, object_pairs_hook=_unique_keys)
        except DuplicateKey as exc:
            raise EfficientTrackError(f"{path}: cannot read the config ({exc})") from exc
        except json.JSONDecodeError as exc:
            raise EfficientTrackError(f"{path}: cannot read the config (not valid JSON: {exc})") from exc
        except ValueError as exc:  # an integer of over 4,300 digits (int()'s limit)
            raise EfficientTrackError(f"{path}: cannot read the config (not valid JSON: {_one_line(exc)})") from exc
        except RecursionError as exc:  # brackets nested beyond Python's recursion limit
            raise EfficientTrackError(f"{path}: cannot read the config (nested too deeply)") from exc
    try:
        return yaml.load(text, Loader=ConfigLoader)
    except yaml.YAMLError as exc:  # DuplicateKey among them
        raise EfficientTrackError(f"{path}: cannot read the config (not valid YAML: {yaml_problem(exc)})") from exc
    except RecursionError as exc:  # brackets nested beyond Python's recursion limit (PyYAML's parser recurses)
        raise EfficientTrackError(f"{path}: cannot read the config (nested too deeply)") from exc
    except Exception as exc:
        # The one broad catch, around yaml.load alone: PyYAML's safe constructors convert a scalar with Python builtins
        # and let out whatever those raise, an open-ended set: ValueError from int() on "!!int 0x" or datetime on
        # "2001-13-01", KeyError from "!!bool maybe", AttributeError from "!!timestamp x", IndexError from an empty
        # "!!int". The text is already read, so what is raised here is about the file's content.
        raise EfficientTrackError(f"{path}: cannot read the config (not valid YAML: {_one_line(exc)})") from exc


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """A JSON object's pairs as a dict; a key given twice raises :class:`DuplicateKey`."""
    data: dict[str, Any] = {}
    for key, value in pairs:
        if key in data:
            raise DuplicateKey(f"the key {key!r} is given twice")
        data[key] = value
    return data


def _one_line(exc: BaseException) -> str:
    """``Type: message``, the message on one line."""
    return f"{type(exc).__name__}: {' '.join(str(exc).split())}"


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


def is_finite_number(value: Any) -> bool:
    """True when ``value`` is an int or float that is finite as a float (not a bool, NaN, ±inf or a huge int)."""
    if not isinstance(value, int | float) or isinstance(value, bool):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:
        return False

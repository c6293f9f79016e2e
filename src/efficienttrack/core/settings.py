"""Typed settings: each field states its bounds and choices beside its type, and one validator checks them all.

A settings class is a frozen dataclass whose fields are made with :func:`setting`; its ``__post_init__`` calls
:func:`check_fields` (types, bounds, choices; ints given for floats and lists given for tuples are converted) and
then checks what involves several fields. The same check runs however the object is made: in Python, from a
YAML/JSON file (:func:`settings_from_dict`) or from ``--set section.field=value`` on the command line
(:func:`parse_override`, laid over the settings' plain form by :func:`merge`). :func:`settings_table` lists a tree
of settings with each field's bounds (``efficienttrack config show``).
"""

from __future__ import annotations

import re
import reprlib
import types
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import MISSING, dataclass, field, fields, is_dataclass
from typing import Any, TypeVar, Union, get_args, get_origin, get_type_hints

import yaml

from efficienttrack.core.configfile import ConfigLoader, is_finite_number
from efficienttrack.core.errors import EfficientTrackError

SettingsT = TypeVar("SettingsT")

DEVICE = (r"auto|cpu|cuda(:\d+)?", "one of auto, cpu, cuda, cuda:N")
"""The one definition of a device name: where torch runs (``auto``: CUDA when there is one); a :func:`setting`'s
``pattern``, and what :func:`~efficienttrack.learn.nets.resolve_device` accepts."""


@dataclass(frozen=True)
class Bounds:
    """What a setting's value may be, beyond its type (for a tuple: each element; None is always allowed by ``X | None``).

    Attributes:
        ge: smallest value allowed (inclusive), or None.
        gt: the value must exceed this, or None.
        le: largest value allowed (inclusive), or None.
        lt: the value must be below this, or None.
        choices: the only values allowed (strings), or None.
        length: a tuple's number of elements, or None for any.
        pattern: a regular expression a string must match whole, and how a reader names what it admits; or None.
    """

    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    choices: tuple[str, ...] | None = None
    length: int | None = None
    pattern: tuple[str, str] | None = None
    lt: float | None = None

    def admits(self, value: Any) -> bool:
        """Whether one (scalar) value lies within the bounds."""
        if self.choices is not None:
            return value in self.choices
        if self.pattern is not None:
            return isinstance(value, str) and re.fullmatch(self.pattern[0], value) is not None
        return (
            (self.ge is None or value >= self.ge)
            and (self.gt is None or value > self.gt)
            and (self.le is None or value <= self.le)
            and (self.lt is None or value < self.lt)
        )

    def describe(self) -> str:
        """The bounds as a reader would write them: ``in (0, 10]``, ``in [0, 1)``, ``≥ 1``, ``one of a, b``; ``""`` if none."""
        if self.choices is not None:
            return f"one of {', '.join(self.choices)}"
        if self.pattern is not None:
            return self.pattern[1]
        low = f"[{_number(self.ge)}" if self.ge is not None else f"({_number(self.gt)}" if self.gt is not None else None
        high = f"{_number(self.le)}]" if self.le is not None else f"{_number(self.lt)})" if self.lt is not None else None
        if low is not None and high is not None:
            return f"in {low}, {high}"
        if low is not None:
            return f"≥ {_number(self.ge)}" if self.ge is not None else f"> {_number(self.gt)}"
        if high is not None:
            return f"≤ {_number(self.le)}" if self.le is not None else f"< {_number(self.lt)}"
        return ""


def _number(value: float | None) -> str:
    """A bound as text: whole numbers in full (``10000000``, ``9223372036854775807``), others as ``%g``."""
    if isinstance(value, int) or (isinstance(value, float) and value.is_integer()):
        return str(int(value))
    return f"{value:g}"


_SHOWN = reprlib.Repr()
_SHOWN.maxlevel, _SHOWN.maxlist, _SHOWN.maxdict, _SHOWN.maxstring, _SHOWN.maxother = 3, 6, 6, 60, 60


def shown(value: Any) -> str:
    """A value as an error message shows it: its repr, cut short (a YAML alias bomb's would not fit in memory)."""
    return _SHOWN.repr(value)


def setting(
    default: Any = MISSING,
    *,
    default_factory: Any = MISSING,
    ge: float | None = None,
    gt: float | None = None,
    le: float | None = None,
    lt: float | None = None,
    choices: Sequence[str] | None = None,
    length: int | None = None,
    pattern: tuple[str, str] | None = None,
    before: Any = MISSING,
) -> Any:
    """A dataclass field with its bounds, checked by :func:`check_fields` (arguments as :class:`Bounds`).

    Args:
        default: the default value.
        default_factory: or a function that makes it (for nested settings).
        ge: smallest value allowed.
        gt: the value must exceed this.
        le: largest value allowed.
        lt: the value must be below this.
        choices: the only values allowed.
        length: a tuple's number of elements.
        pattern: (regular expression a string must match whole, what it admits in words), e.g. :data:`DEVICE`.
        before: for a field added after folders were first written with its class, the value the code had in effect
            before it (what those folders were made with, default or not): :func:`plain_form` leaves the field out at
            that value, so that those folders still match their settings and resume, and a stored form read with
            ``settings_from_dict(..., stored=True)`` takes it where the field is absent.

    Returns:
        The field, to assign in the class body: ``lr: float = setting(1e-3, gt=0, le=MAX_LR)``.
    """
    bounds = Bounds(ge, gt, le, tuple(choices) if choices is not None else None, length, pattern, lt)
    metadata = {"bounds": bounds, "before": before}
    return field(default=default, default_factory=default_factory, metadata=metadata)


def plain_form(settings: Any, every_field: bool = False) -> dict[str, Any]:
    """A settings tree as plain JSON/YAML data (tuples become lists), a field added later left out at its ``before`` value.

    This is the form a folder's identity is compared in and checkpoints store: a field added later does not change the
    identity of settings that keep what the code did before it.

    Args:
        settings: a settings dataclass (nested sections are converted the same way).
        every_field: keep the fields at their ``before`` value too: a file to read back as a file of settings, which
            takes a field it lacks from today's defaults.

    Returns:
        field name → value.
    """
    data: dict[str, Any] = {}
    for spec in fields(settings):
        value = getattr(settings, spec.name)
        if not every_field and spec.metadata.get("before", MISSING) is not MISSING and value == spec.metadata["before"]:
            continue
        if is_dataclass(value):
            data[spec.name] = plain_form(value, every_field)
        elif isinstance(value, tuple):
            data[spec.name] = list(value)
        else:
            data[spec.name] = value
    return data


def inherit(parent: type, name: str, default: Any) -> Any:
    """Field ``name`` of settings class ``parent`` with another default (a subclass redeclaring it keeps its bounds).

    Args:
        parent: the settings class declaring the field.
        name: the field.
        default: the subclass's default.

    Returns:
        The field, to assign in the subclass's body.
    """
    (declared,) = (f for f in fields(parent) if f.name == name)
    return field(default=default, metadata=declared.metadata)


_HINTS: dict[type, dict[str, Any]] = {}
"""Resolved type hints by settings class (``get_type_hints`` evaluates annotation strings: once per class)."""


def _hints(cls: type) -> dict[str, Any]:
    """The resolved type hints of a settings class."""
    if cls not in _HINTS:
        _HINTS[cls] = get_type_hints(cls)
    return _HINTS[cls]


def check_fields(settings: Any) -> None:
    """Check every field of a frozen settings dataclass against its type and bounds; convert ints to floats, lists to tuples.

    Call it first in ``__post_init__``; checks that involve several fields come after it.

    Args:
        settings: the settings object being made.

    Raises:
        EfficientTrackError: ``<Class>.<field> must be …, got …`` for the first field that does not fit.
    """
    owner = type(settings).__name__
    for spec in fields(settings):
        value = getattr(settings, spec.name)
        checked = coerce(_hints(type(settings))[spec.name], value, f"{owner}.{spec.name}", spec.metadata.get("bounds"))
        if checked is not value:
            object.__setattr__(settings, spec.name, checked)


def coerce(hint: Any, value: Any, where: str, bounds: Bounds | None = None) -> Any:
    """``value`` checked against the type ``hint`` and ``bounds``, converted where the type asks (int → float, list → tuple).

    Args:
        hint: int, float, bool, str, ``tuple[float, ...]``/``tuple[int, ...]``, ``X | None``, or a settings dataclass.
        value: the value given.
        where: the field, for the message (``ModelConfig.lr``, ``config.yaml: model: field 'lr'``).
        bounds: what the value may be beyond its type (None: anything of the type).

    Returns:
        The value, converted.

    Raises:
        EfficientTrackError: ``<where> must be …, got …``.
    """
    origin = get_origin(hint)
    if origin in (Union, types.UnionType):
        options = get_args(hint)
        if value is None and type(None) in options:
            return None
        errors = []
        for option in (option for option in options if option is not type(None)):  # ``tuple[int, ...] | str``: the
            try:  # first type that takes the value; when none does, the first type's message
                return coerce(option, value, where, bounds)
            except EfficientTrackError as exc:
                errors.append(exc)
        raise errors[0]
    if isinstance(hint, type) and is_dataclass(hint):
        if not isinstance(value, hint):
            raise EfficientTrackError(f"{where} must be a {hint.__name__}, got {shown(value)}")
        return value
    if origin is tuple:
        (element, *_) = get_args(hint)
        if not isinstance(value, list | tuple):
            raise EfficientTrackError(f"{where} must be a list of {_elements(bounds, element)}, got {shown(value)}")
        try:
            items = tuple(_scalar(element, item, where, bounds) for item in value)
        except EfficientTrackError:
            raise EfficientTrackError(f"{where} must be a list of {_elements(bounds, element)}, got {shown(value)}") from None
        if bounds is not None and bounds.length is not None and len(items) != bounds.length:
            raise EfficientTrackError(f"{where} must be a list of {_elements(bounds, element)}, got {shown(value)}")
        return items
    return _scalar(hint, value, where, bounds)


def _elements(bounds: Bounds | None, element: Any) -> str:
    """``4 finite numbers > 0`` / ``integers ≥ 1``: a tuple's length, element type and bounds, for messages."""
    noun = "integers" if element is int else "finite numbers"
    count = f"{bounds.length} " if bounds is not None and bounds.length is not None else ""
    described = bounds.describe() if bounds is not None else ""
    return f"{count}{noun}" + (f" {described}" if described else "")


def _scalar(hint: Any, value: Any, where: str, bounds: Bounds | None) -> Any:
    """One scalar value checked against its type (bool, int, float, str) and bounds."""
    if hint is bool:
        if not isinstance(value, bool):
            raise EfficientTrackError(f"{where} must be true or false, got {shown(value)}")
        return value
    if hint is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
        kind = "an integer"
    elif hint is float:
        ok = is_finite_number(value)
        kind = "a finite number"
    elif hint is str:
        ok = isinstance(value, str)
        kind = "a string"
    else:
        raise EfficientTrackError(f"{where}: unsupported settings type {hint}")
    if not ok or (bounds is not None and not bounds.admits(value)):
        described = bounds.describe() if bounds is not None else ""
        named = bounds is not None and (bounds.choices is not None or bounds.pattern is not None)
        expected = described if named else f"{kind} {described}".rstrip()
        raise EfficientTrackError(f"{where} must be {expected}, got {shown(value)}")
    return float(value) if hint is float and type(value) is not float else value


def settings_from_dict(cls: type[SettingsT], data: Any, source: str, path: str = "", stored: bool = False) -> SettingsT:
    """Build settings class ``cls`` from a JSON/YAML mapping: unknown names refused, nested sections built the same way.

    Args:
        cls: a settings dataclass; fields whose type is itself a settings dataclass take a mapping.
        data: field name → value; fields not given keep their defaults.
        source: the file or option the data came from, named in messages.
        path: where ``cls`` sits in the tree (``"model."``), prefixed to field names in messages.
        stored: ``data`` is a :func:`plain_form` the package wrote (a checkpoint's config): a field added later that it
            lacks takes its ``before`` value, what the code did when it was written, not today's default.

    Returns:
        The settings.

    Raises:
        EfficientTrackError: not a mapping, an unknown field, or a value its field refuses: ``<source>: <path.field>
            must be …, got …``.
    """
    if not isinstance(data, dict):
        where = f" {path.rstrip('.')}" if path else ""
        raise EfficientTrackError(f"{source}:{where} expected a mapping of {cls.__name__} fields, got {type(data).__name__}")
    names = {spec.name: spec for spec in fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(map(str, set(data) - set(names)))
    if unknown:
        raise EfficientTrackError(
            f"{source}: unknown {cls.__name__} field(s) {', '.join(path + name for name in unknown)}; known: "
            f"{', '.join(sorted(names))}"
        )
    if stored:
        data = {name: spec.metadata["before"] for name, spec in names.items()
                if spec.metadata.get("before", MISSING) is not MISSING} | data  # fmt: skip
    values: dict[str, Any] = {}
    for name, value in data.items():
        hint = _hints(cls)[name]
        if is_dataclass(hint) and isinstance(hint, type):
            values[name] = settings_from_dict(hint, value, source, f"{path}{name}.", stored)
        else:
            values[name] = coerce(hint, value, f"{source}: {path}{name}", names[name].metadata.get("bounds"))
    try:
        return cls(**values)
    except (TypeError, ValueError, EfficientTrackError) as exc:  # the class's own checks name the field; add the source
        raise EfficientTrackError(f"{source}: {exc}") from exc


def merge(base: dict[str, Any], changes: dict[str, Any]) -> dict[str, Any]:
    """``base`` with ``changes`` laid over it; a section (a mapping in both) is merged field by field, recursively.

    Args:
        base: the settings as a plain mapping (``to_dict`` form).
        changes: the fields to change, as given in a file or by a variant.

    Returns:
        A new mapping.
    """
    merged = dict(base)
    for name, value in changes.items():
        if isinstance(value, dict) and isinstance(merged.get(name), dict):
            merged[name] = merge(merged[name], value)
        else:
            merged[name] = value
    return merged


def read_value(raw: str, where: str) -> Any:
    """A value given on the command line, read as YAML: ``5``, ``1e-4``, ``true``, ``null``, ``[9, 2]``; words stay words.

    The one reader of every ``key=value`` option (``--set``, ``--method-set``, ``--system-opt``, ``--machine-opt``).
    ``nan`` and ``inf`` are words (a fault's name), never numbers; an empty value is ``""``.

    Args:
        raw: the text after ``=``.
        where: the option as given, named in messages (``--set 'model.lr=…'``).

    Raises:
        EfficientTrackError: the value is not valid YAML.
    """
    try:
        return yaml.load(raw, Loader=ConfigLoader) if raw.strip() else ""
    except yaml.YAMLError as exc:
        raise EfficientTrackError(f"{where}: the value is not valid YAML ({' '.join(str(exc).split())})") from exc


def parse_override(text: str, option: str = "--set") -> dict[str, Any]:
    """One ``section.field=value`` override as a nested mapping; the value read by :func:`read_value`.

    Args:
        text: e.g. ``model.history=5``.
        option: the option it came from, named in messages.

    Returns:
        E.g. ``{"model": {"history": 5}}``.

    Raises:
        EfficientTrackError: no ``=``, an empty name, or a value that is not valid YAML.
    """
    path, sep, raw = text.partition("=")
    names = path.strip().split(".")
    if not sep or not all(name.strip() for name in names):
        raise EfficientTrackError(f"{option} '{text}': expected section.field=value, e.g. model.history=5")
    override: dict[str, Any] = {names[-1].strip(): read_value(raw, f"{option} '{text}'")}
    for name in reversed(names[:-1]):
        override = {name.strip(): override}
    return override


def settings_table(settings: Any, prefix: str = "") -> Iterator[tuple[str, Any, str]]:
    """Every leaf field of a settings tree with its value and bounds, in declaration order.

    Args:
        settings: a settings dataclass (nested sections are walked).
        prefix: the dotted path of ``settings`` in the tree (``""`` at the root).

    Yields:
        ``(path, value, bounds)``: e.g. ``("model.lr", 0.001, "in (0, 10]")``; ``path`` is what ``--set`` takes.
    """
    for spec in fields(settings):
        value = getattr(settings, spec.name)
        path = f"{prefix}{spec.name}"
        if is_dataclass(value):
            yield from settings_table(value, f"{path}.")
        else:
            bounds = spec.metadata.get("bounds")
            text = bounds.describe() if bounds is not None else ""
            if bounds is not None and bounds.length is not None:
                text = f"{bounds.length} numbers" + (f", each {text}" if text else "")
            optional = type(None) in get_args(_hints(type(settings))[spec.name])
            yield path, value, f"{text} or null".lstrip() if optional and text else ("null allowed" if optional else text)


PRESET_SIZES = ("tiny", "cpu", "paper")
"""The one preset vocabulary of run, study and baselines: ``tiny`` (seconds: tests and smoke runs), ``cpu`` (minutes to
hours on 2 CPU cores), ``paper`` (the paper's settings, a GPU job where the method has them)."""
LEGACY_PRESETS = {"quick": "tiny", "full": "cpu"}
"""The study's and baselines' earlier preset names, still read, with a warning."""


def canonical_preset(name: str) -> str:
    """A preset name in the one vocabulary (:data:`PRESET_SIZES`): an earlier name is translated, with a warning.

    Args:
        name: the name given (``--preset``, a library call).

    Returns:
        The name, or its new name for ``quick`` (``tiny``) and ``full`` (``cpu``).
    """
    if name in LEGACY_PRESETS:
        warnings.warn(f"preset '{name}' is now called '{LEGACY_PRESETS[name]}'", FutureWarning, stacklevel=2)
        return LEGACY_PRESETS[name]
    return name

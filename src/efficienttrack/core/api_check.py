"""The public Python API's argument check: a wrong type is one EfficientTrackError naming the argument.

``efficienttrack.run``, ``load_policy``, ``export`` and the other top-level names (``efficienttrack.API``) are called
through :func:`checked`: the arguments are bound to the function's signature (a missing or unknown one is named) and
each is checked against its annotation, shallowly (a ``Sequence[Reference]`` must be a sequence, not a string; its
items are the function's to check). Without it, ``et.load_system(5)`` ended in ``TypeError: argument of type 'int' is
not iterable`` from deep inside.
"""

from __future__ import annotations

import collections.abc
import functools
import inspect
import numbers
import os
import types
import typing
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar, Union, get_args, get_origin

from efficienttrack.core.errors import EfficientTrackError, MissingExtraError, missing_extra
from efficienttrack.core.settings import shown

F = TypeVar("F", bound=Callable[..., Any])


def checked(name: str, function: F) -> F:
    """``function`` with its arguments checked against its signature and annotations before it runs.

    Args:
        name: the public name, for messages (``efficienttrack.<name>``).
        function: the function; annotations that cannot be resolved are not checked.

    Returns:
        The checking wrapper (the same signature and docstring).
    """
    signature = inspect.signature(function)
    try:
        hints = typing.get_type_hints(function)
    except Exception:  # names imported for type checking only: check what the signature alone can
        hints = {}

    @functools.wraps(function)
    def call(*args: Any, **kwargs: Any) -> Any:
        try:
            bound = signature.bind(*args, **kwargs)
        except TypeError as exc:
            raise EfficientTrackError(f"efficienttrack.{name}: {exc}") from None
        for parameter, value in bound.arguments.items():
            hint = hints.get(parameter)
            if signature.parameters[parameter].kind in (inspect.Parameter.VAR_POSITIONAL, inspect.Parameter.VAR_KEYWORD):
                continue
            if hint is not None and not admits(hint, value):
                raise EfficientTrackError(
                    f"efficienttrack.{name}: argument '{parameter}' must be {describe(hint)}, got "
                    f"{type(value).__name__} {shown(value)}"
                )
        try:
            return function(*args, **kwargs)
        except MissingExtraError:
            raise
        except ModuleNotFoundError as exc:  # a library the function imports when it runs: name the extra
            missing = missing_extra(exc, f"efficienttrack.{name}")
            if missing is None:
                raise
            raise missing from exc

    return typing.cast(F, call)


def admits(hint: Any, value: Any) -> bool:
    """Whether ``value`` fits the type ``hint`` at its top level (containers are not looked into).

    Args:
        hint: a resolved annotation.
        value: the argument.
    """
    origin = get_origin(hint)
    if hint is Any or isinstance(hint, TypeVar):
        return True
    if origin in (Union, types.UnionType):
        return any(admits(option, value) for option in get_args(hint))
    if hint is type(None):
        return value is None
    if origin is type:
        return isinstance(value, type)
    if origin is not None:
        hint = origin
    if hint is bool:
        return isinstance(value, bool)
    if hint is int:
        return isinstance(value, numbers.Integral) and not isinstance(value, bool)
    if hint is float:
        return isinstance(value, numbers.Real) and not isinstance(value, bool)
    if hint is Path:
        return isinstance(value, os.PathLike)
    if hint in (collections.abc.Sequence, collections.abc.Iterable, list, tuple) and isinstance(value, str | bytes):
        return False
    if not isinstance(hint, type):
        return True
    try:
        return isinstance(value, hint)
    except TypeError:  # a Protocol without runtime checks: the function checks what it needs
        return True


def describe(hint: Any) -> str:
    """The type ``hint`` as a reader would write it: ``a string or a path``, ``a sequence``, ``an integer``.

    Args:
        hint: a resolved annotation.
    """
    if get_origin(hint) in (Union, types.UnionType):
        return " or ".join(describe(option) for option in get_args(hint))
    origin = get_origin(hint) or hint
    words = {
        type(None): "None",
        bool: "true or false",
        int: "an integer",
        float: "a number",
        str: "a string",
        Path: "a path",
        collections.abc.Sequence: "a sequence (a list or a tuple)",
        collections.abc.Iterable: "a list of them",
        dict: "a dict",
        type: "a class",
    }
    return words.get(origin, f"a {getattr(origin, '__name__', str(origin))}")

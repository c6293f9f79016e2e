"""Meta-test (as python-control's ``docstrings_test``): every public function and method documents its parameters.

Walks the whole ``efficienttrack`` package with :func:`pkgutil.walk_packages` and, for each public function and each
public method (instance, class and static) of a public class defined in that module, checks that the docstring
mentions every parameter other than ``self``/``cls`` by name, as a whole word.  A hand-written ``__init__`` is checked
against the class docstring together with its own, since constructor arguments are documented on the class.
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import pkgutil
import re
import types
from collections.abc import Callable, Iterator
from typing import NamedTuple

import efficienttrack


class Target(NamedTuple):
    qualname: str
    function: Callable
    doc: str
    owner: type | None


def _modules() -> Iterator[types.ModuleType]:
    yield efficienttrack
    for info in pkgutil.walk_packages(efficienttrack.__path__, "efficienttrack."):
        yield importlib.import_module(info.name)


def _is_protocol(cls: type | None) -> bool:
    return cls is not None and bool(getattr(cls, "_is_protocol", False))


def _is_typer_command(module: types.ModuleType, name: str) -> bool:
    # Typer commands of the CLI: each option carries a ``help=`` text, which ``--help`` shows and which is the
    # user-facing documentation of that parameter; the docstring is the command summary and need not repeat them.
    return module.__name__.startswith("efficienttrack.cli.") and name.endswith("_command")


def _targets() -> Iterator[Target]:
    for module in _modules():
        for name, obj in vars(module).items():
            if name.startswith("_") or getattr(obj, "__module__", None) != module.__name__:
                continue
            qual = f"{module.__name__}.{name}"
            if inspect.isfunction(obj):
                if not _is_typer_command(module, name):
                    yield Target(qual, obj, inspect.getdoc(obj) or "", None)
            elif inspect.isclass(obj):
                for attr, member in vars(obj).items():
                    fn = member.__func__ if isinstance(member, classmethod | staticmethod) else member
                    if not inspect.isfunction(fn):
                        continue
                    if attr == "__init__":
                        # Dataclass-generated ``__init__``s are skipped: the fields are documented by attribute
                        # docstrings.  ``typing.Protocol`` synthesizes an ``__init__`` of its own (``*args,
                        # **kwargs``), which is no part of the interface.
                        if dataclasses.is_dataclass(obj) or _is_protocol(obj):
                            continue
                        doc = "\n".join(d for d in (inspect.getdoc(obj), inspect.getdoc(fn)) if d)
                        yield Target(f"{qual}.__init__", fn, doc, obj)
                    elif not attr.startswith("_"):
                        yield Target(f"{qual}.{attr}", fn, inspect.getdoc(fn) or "", obj)


def _undocumented(target: Target) -> list[str]:
    lost = []
    for p in inspect.signature(target.function).parameters.values():
        if p.name in ("self", "cls"):
            continue
        # ``*args``/``**kwargs`` of Protocol stubs only pass through to the implementations, which document them.
        if _is_protocol(target.owner) and p.kind in (p.VAR_POSITIONAL, p.VAR_KEYWORD):
            continue
        if not re.search(rf"(?<!\w){re.escape(p.name)}(?!\w)", target.doc):
            lost.append(p.name)
    return lost


def test_walk_finds_functions_and_methods() -> None:
    names = {t.qualname for t in _targets()}
    assert len(names) > 50
    assert "efficienttrack.core.fileio.write_json" in names  # function
    assert "efficienttrack.systems.hydraulic.HydraulicParams.replace" in names  # method
    assert "efficienttrack.data.records.EpisodeRecord.load" in names  # classmethod
    assert "efficienttrack.systems.protocol.BatchedSystem.__init__" in names  # hand-written constructor
    assert "efficienttrack.systems.hydraulic.HydraulicParams.__init__" not in names  # dataclass-generated
    assert "efficienttrack.cli.common.parse_options" in names
    assert not any(n.startswith("efficienttrack.cli.") and n.endswith("_command") for n in names)


def test_check_catches_a_missing_parameter() -> None:
    def f(alpha: int, beta: int) -> None:
        """Use ``alpha`` and the alphabet."""

    assert _undocumented(Target("f", f, inspect.getdoc(f) or "", None)) == ["beta"]


def test_every_parameter_is_documented() -> None:
    gaps = []
    for target in _targets():
        if not target.doc:
            gaps.append(f"{target.qualname}: no docstring")
        elif lost := _undocumented(target):
            gaps.append(f"{target.qualname}: {', '.join(lost)}")
    assert not gaps, "public functions/methods whose docstring does not mention these parameters:\n" + "\n".join(gaps)

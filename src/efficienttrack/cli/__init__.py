"""The ``efficienttrack`` command line: every subcommand is a thin wrapper over a library function.

One module per command group: :mod:`~efficienttrack.cli.data` (references, metrics, conversion, collection),
:mod:`~efficienttrack.cli.runs` (run, demo, evaluate), :mod:`~efficienttrack.cli.learning` (training, model error,
rounds), :mod:`~efficienttrack.cli.deployment` (export, deploy), :mod:`~efficienttrack.cli.limits` (a machine's guard
limits from its logs, checked), :mod:`~efficienttrack.cli.sim` (the simulator's fit), :mod:`~efficienttrack.cli.study`
(the comparative study), :mod:`~efficienttrack.cli.ablate` (the ablations), :mod:`~efficienttrack.cli.config` (the
settings tree); :mod:`~efficienttrack.cli.common` holds the app and what several commands share. Importing a module
registers its commands, in the order ``--help`` lists them.

The command line imports only the core install's libraries: a command that needs an extra's (torch, Ray…) imports
them in its body, and :func:`main` turns a missing one into one line naming the extra to install.
"""

from __future__ import annotations

import sys
import warnings
from typing import Annotated

import typer

import efficienttrack
from efficienttrack.core.errors import EfficientTrackError, MissingExtraError, missing_extra
from efficienttrack.core.fileio import os_error_text

# isort: split
# Importing a command module registers its commands, and in this order ``efficienttrack --help`` lists them.
from efficienttrack.cli import data, runs, learning, deployment, limits, sim, study, ablate, config  # noqa: F401, I001

# isort: split
from efficienttrack.cli.common import app, parse_options, wide_console
from efficienttrack.cli.config import config_app
from efficienttrack.cli.data import refs_app
from efficienttrack.cli.sim import parse_ints, sim_app

__all__ = ["app", "main", "parse_ints", "parse_options", "refs_app", "sim_app", "wide_console"]

app.add_typer(refs_app, name="refs")
app.add_typer(sim_app, name="sim")
app.add_typer(config_app, name="config")


def _print_version(value: bool) -> None:
    if value:
        typer.echo(f"efficienttrack {efficienttrack.__version__}")
        raise typer.Exit()


@app.callback()
def _options(
    version: Annotated[
        bool, typer.Option("--version", help="Print the version and exit.", callback=_print_version, is_eager=True)
    ] = False,
) -> None:
    """Options of the ``efficienttrack`` command itself (before the subcommand)."""


def _one_line_warning(
    message: Warning | str, category: type[Warning], filename: str, lineno: int, line: str | None = None
) -> str:
    return f"warning: {message}\n"


def main() -> None:
    """Entry point: run the app; user-facing errors, a file the system refuses and a missing extra: one line, exit code 2."""
    warnings.formatwarning = _one_line_warning
    try:
        app()
    except ModuleNotFoundError as exc:
        missing = exc if isinstance(exc, MissingExtraError) else missing_extra(exc, "this command")
        if missing is None:  # a module of the core install or of the package itself: a broken install or a bug
            raise
        typer.secho(f"error: {missing}", fg=typer.colors.RED, err=True)
        sys.exit(2)
    except (EfficientTrackError, OSError) as exc:
        if isinstance(exc, OSError) and exc.errno is None:  # not the system refusing a file: a bug, keep its traceback
            raise
        typer.secho(f"error: {os_error_text(exc) if isinstance(exc, OSError) else exc}", fg=typer.colors.RED, err=True)
        sys.exit(2)

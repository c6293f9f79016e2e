"""The ``config`` commands: the settings tree a command would run with, printed as a YAML file that ``--config`` reads."""

from __future__ import annotations

import json
from typing import Annotated

import typer

from efficienttrack.cli.common import ConfigOpt, SetOpt, _settings

config_app = typer.Typer(help="The settings tree: what run, train-model, train-policy, round, study and ablate take.")


@config_app.command("show")
def show_command(
    preset_name: Annotated[
        str, typer.Argument(metavar="[PRESET]", help="paper, cpu, fastset or tiny (default: cpu, the library's defaults).")
    ] = "cpu",
    config: ConfigOpt = None,
    overrides: SetOpt = None,
) -> None:
    """Print every setting of PRESET, amended by --config and --set, with its bounds; the output is a valid --config file.

    Each line is ``field: value  # bounds``; ``--set section.field=value`` changes one of them on any command that trains.
    """
    from efficienttrack.core.settings import settings_table

    cfg = _settings(preset_name, config, overrides)
    rows = list(settings_table(cfg))
    width = max(len(path.rsplit(".", 1)[-1]) + 2 * path.count(".") + len(json.dumps(value)) for path, value, _ in rows)
    section = None
    typer.echo(
        f"# efficienttrack settings: preset {preset_name}"
        + (f", {config}" if config else "")
        + "".join(f", --set {text}" for text in overrides or ())
    )
    for path, value, bounds in rows:
        *parents, name = path.split(".")
        if parents and parents[0] != section:
            section = parents[0]
            typer.echo(f"{section}:")
        elif not parents:
            section = None
        line = f"{'  ' * len(parents)}{name}: {json.dumps(value)}"
        note = "follows seed" if path == "collect.seed" else bounds
        typer.echo(f"{line:<{width + 2}}  # {note}" if note else line)

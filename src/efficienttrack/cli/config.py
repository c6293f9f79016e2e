"""The ``config`` commands: the settings tree a command would run with, printed as a YAML file that ``--config`` reads."""

from __future__ import annotations

import json
from typing import Annotated, Any

import typer

from efficienttrack.cli.common import ConfigOpt, SetOpt, _settings
from efficienttrack.core.errors import EfficientTrackError

config_app = typer.Typer(help="The settings tree: what run, train-model, train-policy, round, study and ablate take.")


@config_app.command("show")
def show_command(
    preset_name: Annotated[
        str, typer.Argument(metavar="[PRESET]", help="paper, cpu, fastset or tiny (default: cpu, the library's defaults).")
    ] = "cpu",
    config: ConfigOpt = None,
    overrides: SetOpt = None,
    method: Annotated[
        str | None,
        typer.Option(
            "--method",
            help="A study method's settings instead (sac, ppo, tdmpc, supertrack, ilc, or efficienttrack's open loop), "
            "of PRESET as the baselines name it; study --method-set METHOD.FIELD=VALUE changes them.",
        ),
    ] = None,
) -> None:
    """Print every setting of PRESET, amended by --config and --set, with its bounds; the output is a valid --config file.

    Each line is ``field: value  # bounds``; ``--set section.field=value`` changes one of them on any command that trains.
    """
    from efficienttrack.core.settings import settings_table

    if method is not None:
        from efficienttrack.study.methods import METHODS, preset_settings, settable

        if config is not None or overrides:
            raise EfficientTrackError("config show --method: takes no --config or --set (study --method-set changes it)")
        if method not in settable():
            known = ", ".join(settable())
            if method in METHODS and METHODS[method].run_settings:
                raise EfficientTrackError(f"--method {method}: takes the run's settings: efficienttrack config show "
                                          f"--preset {preset_name} lists them, study --set changes them")  # fmt: skip
            raise EfficientTrackError(f"--method {method}: " + ("has no settings" if method in METHODS else "unknown") +
                                      f"; methods with settings: {known}")  # fmt: skip
        typer.echo(f"# {method} settings of the study's preset {preset_name} (study --method-set {method}.FIELD=VALUE)")
        _print(list(settings_table(preset_settings(method, preset_name))))
        return
    cfg = _settings(preset_name, config, overrides)
    typer.echo(
        f"# efficienttrack settings: preset {preset_name}"
        + (f", {config}" if config else "")
        + "".join(f", --set {text}" for text in overrides or ())
    )
    _print(list(settings_table(cfg)))


def _print(rows: list[tuple[str, Any, str]]) -> None:
    """Settings rows (``settings_table``) as YAML, each line with its bounds as a comment."""
    width = max(len(path.rsplit(".", 1)[-1]) + 2 * path.count(".") + len(json.dumps(value)) for path, value, _ in rows)
    section = None
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

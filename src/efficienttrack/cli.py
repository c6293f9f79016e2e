"""The ``efficienttrack`` command line: every subcommand is a thin wrapper over a library function."""

from __future__ import annotations

import sys

import typer

from efficienttrack.errors import EfficientTrackError

app = typer.Typer(
    help="EfficientTrack: high-precision excavator trajectory tracking from learned closed-loop dynamics.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)
refs_app = typer.Typer(help="Reference trajectories: generate and plot.", no_args_is_help=True)
sim_app = typer.Typer(help="The built-in hydraulic simulator: calibrate and check fidelity.", no_args_is_help=True)
app.add_typer(refs_app, name="refs")
app.add_typer(sim_app, name="sim")


def parse_options(pairs: list[str] | None, flag: str = "--system-opt") -> dict[str, object]:
    """Turn repeated ``key=value`` strings into keyword options (numbers and booleans parsed)."""
    options: dict[str, object] = {}
    for pair in pairs or []:
        key, sep, raw = pair.partition("=")
        if not sep or not key:
            raise EfficientTrackError(f"{flag} '{pair}': expected key=value")
        value: object = raw
        if raw.lower() in ("true", "false"):
            value = raw.lower() == "true"
        else:
            for cast in (int, float):
                try:
                    value = cast(raw)
                    break
                except ValueError:
                    continue
        options[key] = value
    return options


def main() -> None:
    """Entry point: run the app and turn user-facing errors into one clean line and exit code 2."""
    try:
        app()
    except EfficientTrackError as exc:
        typer.secho(f"error: {exc}", fg=typer.colors.RED, err=True)
        sys.exit(2)

"""What the commands share: the Typer app, the options several commands take, and the helpers behind them."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import output_lock
from efficienttrack.core.settings import read_value

TABLE_WIDTH = 132
"""Characters the columns of a metrics table take besides its row labels."""

app = typer.Typer(
    help="EfficientTrack: high-precision excavator trajectory tracking from learned closed-loop dynamics.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)

RecursiveOpt = Annotated[
    bool, typer.Option("--recursive", "-r", help="Read subfolders too (a folder alone means the episodes directly in it).")
]

SystemOpt = Annotated[
    str | None,
    typer.Option(
        "--system",
        help="Closed-loop system: built-in name (xe75; paper, the paper's simulator; learned with --system-opt "
        "model=CKPT) or module.path:callable.",
    ),
]

PlantOpt = Annotated[
    str | None,
    typer.Option("--plant", help="Plant (PWM level) wrapped with the PD controller: xe75, paper or module.path:callable."),
]

PdOpt = Annotated[
    str | None,
    typer.Option("--pd", help="PD gains for --plant: preset name (xe75, paper) or a JSON file (default: a built-in plant's)."),
]

SystemOpts = Annotated[list[str] | None, typer.Option("--system-opt", help="key=value option of the system (repeatable).")]

MachineOpt = Annotated[
    str | None, typer.Option("--machine", help="A real machine's adapter, module.path:callable (needs --limits).")
]
MachineOpts = Annotated[list[str] | None, typer.Option("--machine-opt", help="key=value option of the adapter (repeatable).")]
BetweenOpt = Annotated[
    str,
    typer.Option(
        "--between-episodes",
        help="When the machine is not at a reference's start: approach it slowly through the loop (logged in "
        "approach/, never scored or trained on), prompt the operator to bring it there and press Enter, or stop.",
    ),
]
ArmOpt = Annotated[bool, typer.Option("--arm", help="Allow the machine to move (nothing is sent without it).")]
FastOpt = Annotated[
    bool, typer.Option("--fast", help="Simulator only: a simulated clock, as fast as it computes (no real-time timing).")
]
LimitsOpt = Annotated[
    Path | None,
    typer.Option(
        "--limits",
        help="The guard's joint limits and adjustment bounds: xe75 (shipped) or a YAML/JSON file (amends the system's; "
        "`efficienttrack limits` proposes one from logs).",
    ),
]

DeviceOpt = Annotated[str, typer.Option("--device", help="auto, cpu or cuda.")]

PresetOpt = Annotated[
    str, typer.Option("--preset", help="Settings preset: paper, cpu, fastset or tiny (config show lists them).")
]

ConfigOpt = Annotated[Path | None, typer.Option("--config", help="YAML/JSON of settings changing the preset's.")]

SetOpt = Annotated[
    list[str] | None,
    typer.Option(
        "--set",
        help="Change one setting, after --config: section.field=value, e.g. model.history=5 (repeatable; "
        "`efficienttrack config show` lists them).",
    ),
]

RunSeedOpt = Annotated[int | None, typer.Option("--seed", help="Seed of collection noise and training.")]

RunDeviceOpt = Annotated[str | None, typer.Option("--device", help="auto, cpu or cuda.")]

ThreadsOpt = Annotated[
    int,
    typer.Option("--threads", help="torch CPU threads (1: fastest for cpu-preset networks on 2 shared cores; 0: default)."),
]


def between(value: str) -> str:
    """``--between-episodes``: one of :data:`~efficienttrack.deploy.deployment.BETWEEN_EPISODES`, else a clear error.

    Args:
        value: as given on the command line.
    """
    from efficienttrack.deploy.deployment import BETWEEN_EPISODES

    if value not in BETWEEN_EPISODES:
        raise EfficientTrackError(f"--between-episodes {value}: expected one of {', '.join(BETWEEN_EPISODES)}")
    if value == "prompt" and not sys.stdin.isatty():
        raise EfficientTrackError("--between-episodes prompt: asks an operator at a terminal, and the input is none")
    return value


def parse_options(pairs: list[str] | None, flag: str = "--system-opt") -> dict[str, object]:
    """Turn repeated ``key=value`` strings into keyword options, each value read as ``--set`` reads one.

    Args:
        pairs: the ``key=value`` strings as given on the command line (``None`` when the option was not used).
        flag: the option's name, used in error messages.

    Returns:
        ``{key: value}``: numbers, booleans and lists where the value reads as one
        (:func:`~efficienttrack.core.settings.read_value`; ``nan`` and ``inf`` stay words), else the string.

    Raises:
        EfficientTrackError: a string without ``=``, with an empty key, or a value that is not valid YAML.
    """
    options: dict[str, object] = {}
    for pair in pairs or []:
        key, sep, raw = pair.partition("=")
        if not sep or not key:
            raise EfficientTrackError(f"{flag} '{pair}': expected key=value")
        options[key] = read_value(raw, f"{flag} '{pair}'")
    return options


def _system_spec(system: str | None, plant: str | None, pd: str | None, options: list[str] | None, limits: Path | None = None):
    """The system the ``--system``/``--plant``/``--pd``/``--system-opt``/``--limits`` options name, not yet opened."""
    from efficienttrack.systems.spec import SystemSpec

    return SystemSpec(
        system=system,
        plant=plant,
        pd=pd,
        options=tuple(parse_options(options).items()),
        limits=None if limits is None else str(limits),
    )


def _settings(preset_name: str, config: Path | None, overrides: list[str] | None, **options: object):
    """The settings tree of a command: preset, ``--config``, ``--set``, then the command's own options (None: not given).

    Args:
        preset_name: the ``--preset``.
        config: the ``--config`` file, or None.
        overrides: the ``--set`` strings.
        **options: top-level fields given by their own options (``seed``, ``device``, ``rounds``…), applied last.

    Returns:
        The :class:`~efficienttrack.workflow.config.RunConfig`.
    """
    from efficienttrack.workflow.config import amend, resolve_settings

    cfg = resolve_settings(preset_name, config, overrides)
    for name, value in options.items():
        if value is not None:
            cfg = amend(cfg, {name: value}, f"--{name.replace('_', '-')} {value}")
    return cfg


def _lock(ctx: typer.Context, out: Path, folder: bool = True, resumable: bool = True) -> None:
    """Hold the lock of output ``out`` (a folder, else a checkpoint) until the command ``ctx`` ends, however it ends.

    A resumable command stopped by Ctrl-C (or SIGTERM, SIGHUP) says what was kept and how to go on.
    """
    ctx.with_resource(output_lock(out, folder=folder))
    if resumable:
        ctx.with_resource(_on_interrupt(out))


@contextmanager
def _on_interrupt(out: Path) -> Iterator[None]:
    """Within the block, an interrupt is followed by one line naming what was kept and how to resume (exit code 130)."""
    try:
        yield
    except KeyboardInterrupt as exc:
        from efficienttrack.core.stop_signals import interrupt_name

        typer.secho(
            f"{interrupt_name(exc)}: stopped; what finished is kept in {out}: rerun the same command to go on from "
            "there, or add --force to start afresh",
            fg=typer.colors.YELLOW,
            err=True,
        )
        raise


def _set_threads(threads: int) -> None:
    """Let torch use ``threads`` CPU threads (the ``--threads`` option; 0 leaves torch's default)."""
    import torch

    if threads < 0:
        raise EfficientTrackError(f"--threads {threads}: expected ≥ 0")
    if threads:
        torch.set_num_threads(threads)


def wide_console(label_width: int = 8) -> Console:
    """A console wide enough for a metrics table whose row labels are ``label_width`` characters long.

    Figures are never cropped or folded, also on a narrow terminal or when the output is not a terminal.

    Args:
        label_width: length of the longest row label (a method name or a path).
    """
    return Console(width=max(Console().width, TABLE_WIDTH + label_width))

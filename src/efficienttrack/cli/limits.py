"""The ``limits`` command: propose a machine's guard limits from its logs (``--from-logs``), or check a limits file."""

from __future__ import annotations

import math
import shlex
from pathlib import Path
from typing import Annotated

import typer

import efficienttrack
from efficienttrack.cli.common import RecursiveOpt, _lock, app
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import check_output_file
from efficienttrack.core.joints import JOINT_NAMES, SWING
from efficienttrack.systems.limits import DEFAULT_LIMITS, LIMITS_PRESETS, GuardLimits, resolve_limits_path
from efficienttrack.systems.limits_from_logs import (
    DEFAULT_MARGIN,
    DEFAULT_SPEED_FACTOR,
    check_proposal_options,
    write_limits,
)
from efficienttrack.systems.ros2_limits import from_ros2, is_ros2, to_ros2

COLUMNS = (
    ("q_min", "q_min", "°", "rad"),
    ("q_max", "q_max", "°", "rad"),
    ("max_speed", "max_speed", "°/s", "rad/s"),
    ("max_adjust", "max_adjust", "°", "rad"),
    ("max_adjust_rate", "max_adjust_rate", "°/step", "rad/step"),
)
"""The per-joint fields of the ``--check`` table: field, heading, report unit (degrees), file unit (radians)."""


def _cell(value: float, deg: str, rad: str) -> str:
    """One value in degrees, then in radians: ``-31.51° (-0.5500 rad)``."""
    return f"{math.degrees(value):.2f}{deg} ({value:.4f} {rad})"


def limits_report(limits: GuardLimits) -> list[str]:
    """The limits per joint, in degrees and radians, as text lines (a table, then the swing and ``stale_steps``).

    Args:
        limits: the limits to show.

    Returns:
        The lines, without newlines.
    """
    cells = [[_cell(getattr(limits, f)[j], deg, rad) for f, _, deg, rad in COLUMNS] for j in range(len(JOINT_NAMES))]
    widths = [max(len(heading), *(len(row[i]) for row in cells)) for i, (_, heading, _, _) in enumerate(COLUMNS)]
    lines = ["joint   " + "  ".join(column[1].rjust(w) for column, w in zip(COLUMNS, widths, strict=True))]
    for joint, row in zip(JOINT_NAMES, cells, strict=True):
        lines.append(f"{joint:<8}" + "  ".join(cell.rjust(w) for cell, w in zip(row, widths, strict=True)))
    lo, hi = limits.q_min[SWING], limits.q_max[SWING]
    swing = (
        "unlimited" if lo <= -math.pi and hi >= math.pi else f"limited to [{math.degrees(lo):.2f}°, {math.degrees(hi):.2f}°]"
    )
    lines.append(f"swing: compared wrapped to (−180°, 180°]; {swing}")
    stale = "not checked (null)" if limits.stale_steps is None else f"{limits.stale_steps} repeated observations in a row"
    lines.append(f"stale_steps: {stale}")
    return lines


def _check(spec: str) -> GuardLimits:
    """``limits --check``: validate a limits file (or preset), print what it resolves to, and return it."""
    from efficienttrack.core.configfile import read_mapping_file

    path = resolve_limits_path(spec)
    limits = GuardLimits.load(spec)
    given = read_mapping_file(path)  # a valid mapping: load read it already
    if is_ros2(given):
        given = from_ros2(given, str(path))
    left_out = [name for name in DEFAULT_LIMITS.to_dict() if name not in given]
    name = f"{spec} ({path})" if spec in LIMITS_PRESETS else str(path)
    typer.echo(f"{name}: valid limits (joint order boom, arm, bucket, swing)")
    for line in limits_report(limits):
        typer.echo(f"  {line}")
    if left_out:
        typer.echo(
            f"  left out: {', '.join(left_out)} (shown with the defaults; used with a system, they keep the system's own)"
        )
    return limits


def _command(paths: list[Path], out: Path, margin: float, speed_factor: float, recursive: bool) -> str:
    """The command line that proposes these limits, for the file's header."""
    words = ["efficienttrack", "limits", "--from-logs", *map(str, paths), "--out", str(out)]
    words += ["--margin", f"{margin:g}", "--speed-factor", f"{speed_factor:g}", *(["--recursive"] if recursive else [])]
    return shlex.join(words)


@app.command("limits")
def limits_command(
    ctx: typer.Context,
    paths: Annotated[
        list[Path] | None,
        typer.Argument(
            help="With --from-logs: episode files or folders (.npz, our .csv, upstream .npy/.csv).", show_default=False
        ),
    ] = None,
    from_logs: Annotated[
        bool,
        typer.Option("--from-logs", help="Propose limits from the episode logs PATHS: limits --from-logs DIR... --out FILE."),
    ] = False,
    out: Annotated[
        Path | None,
        typer.Option(
            "--out", help="Limits file to write: YAML with a comment header saying why, or JSON when it ends in .json."
        ),
    ] = None,
    margin: Annotated[
        float, typer.Option("--margin", help="Widening of the joint range seen, on each side, rad (in [0, π]).")
    ] = DEFAULT_MARGIN,
    speed_factor: Annotated[
        float, typer.Option("--speed-factor", help="max_speed over the top speed seen (in [1, 100]).")
    ] = DEFAULT_SPEED_FACTOR,
    check: Annotated[
        str | None,
        typer.Option(
            "--check",
            help=f"Validate a limits file (or a preset: {', '.join(LIMITS_PRESETS)}) and print its limits per joint.",
        ),
    ] = None,
    recursive: RecursiveOpt = False,
    ros2: Annotated[
        bool,
        typer.Option("--ros2", help="Write --out as a ros2_control (MoveIt) joint_limits.yaml instead of the guard's schema."),
    ] = False,
    joint_names: Annotated[
        str,
        typer.Option("--joint-names", help="With --ros2: the machine's joint names, boom, arm, bucket, swing order."),
    ] = ",".join(JOINT_NAMES),
) -> None:
    """Propose a machine's guard limits from its own logs (--from-logs), or check a limits file (--check).

    The proposal prints one line per field with what the logs show and the margin or factor applied, and writes the
    file atomically; docs/reference.md ("Limits files") gives the schema and the rules. A ros2_control
    joint_limits.yaml is read wherever a limits file is; --check FILE --out OUT converts one file into the other format.
    """
    if (ros2 or joint_names != ",".join(JOINT_NAMES)) and out is None:
        raise EfficientTrackError("limits: --ros2 and --joint-names say how --out is written; give --out FILE")
    if joint_names != ",".join(JOINT_NAMES) and not ros2:
        raise EfficientTrackError("limits: --joint-names names the joints of a ros2_control file; give --ros2 too")
    names = [name.strip() for name in joint_names.split(",")] if ros2 else None
    if names is not None:
        to_ros2(DEFAULT_LIMITS.to_dict(), names)  # refuses names that would not read back, before any work
    if check is not None:
        if from_logs or paths:
            raise EfficientTrackError("limits: give --check FILE [--out FILE], or --from-logs PATHS... --out FILE")
        limits = _check(check)
        if out is not None:
            check_output_file(out)
            _lock(ctx, out, folder=False, resumable=False)
            write_limits(limits, out, [f"Guard limits of {check}, checked by efficienttrack {efficienttrack.__version__}"],
                         ros2_names=names)  # fmt: skip
            typer.echo(f"wrote {out}" + (" (ros2_control joint_limits.yaml)" if ros2 else ""))
        return
    if not from_logs:
        what = f"{paths[0]}: episode logs need --from-logs" if paths else "nothing to do"
        raise EfficientTrackError(f"limits: {what}; give --from-logs PATHS... --out FILE, or --check FILE")
    if not paths:
        raise EfficientTrackError("limits --from-logs: give one or more episode files or folders")
    if out is None:
        raise EfficientTrackError("limits --from-logs: give --out FILE (YAML, or JSON when it ends in .json)")
    check_proposal_options(margin, speed_factor, "--")
    check_output_file(out)
    _lock(ctx, out, folder=False, resumable=False)  # two proposals at once would replace each other's file
    from efficienttrack.data.records import load_records
    from efficienttrack.systems.limits_from_logs import propose_limits

    records = load_records(paths, recursive=recursive)
    limits, reasons = propose_limits(records, margin=margin, speed_factor=speed_factor)
    steps = sum(map(len, records))
    header = [
        f"Guard limits proposed from a machine's own logs by efficienttrack {efficienttrack.__version__}:",
        f"  {_command(paths, out, margin, speed_factor, recursive)}",
        f"Logs: {len(records)} episode(s), {steps:,} steps, from {', '.join(map(str, paths))}",
        'Joint order boom, arm, bucket, swing; rad, rad/s, rad per step (docs/reference.md, "Limits files").',
        "Why each value (check it with: efficienttrack limits --check FILE):",
        *(f"  {reason}" for reason in reasons),
    ]
    for reason in reasons:
        typer.echo(reason)
    write_limits(limits, out, header, ros2_names=names)
    typer.echo(f"wrote {out}: limits from {len(records)} episode(s), {steps:,} steps; per joint:")
    for line in limits_report(limits):
        typer.echo(f"  {line}")

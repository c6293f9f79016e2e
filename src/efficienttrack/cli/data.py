"""Commands on references and episode data: ``refs generate``/``refs plot``, ``metrics``, ``convert``, ``collect``."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from efficienttrack.cli.common import (
    ArmOpt,
    BetweenOpt,
    FastOpt,
    LimitsOpt,
    MachineOpt,
    MachineOpts,
    PdOpt,
    PlantOpt,
    RecursiveOpt,
    SystemOpt,
    SystemOpts,
    _lock,
    _system_spec,
    app,
    between,
    parse_options,
    wide_console,
)
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import check_output_file, check_output_folder, finite_json, prepare_output_folder
from efficienttrack.data.metrics import metrics_by_path, metrics_table, rounded, write_metrics_csv
from efficienttrack.data.records import RECORD_SUFFIXES, find_record_files, load_record, record_files, save_records
from efficienttrack.data.tabular import MAX_GAP, TABLE_SUFFIXES, check_options, needs_import, read_table
from efficienttrack.workflow.collect import CollectConfig

refs_app = typer.Typer(help="Reference trajectories: generate and plot.", no_args_is_help=True)

REFERENCES_PLOT = "references.png"
"""Default name of the plot ``refs plot`` draws next to the references."""

COLLECT = CollectConfig()
"""Where the ``collect`` options take their defaults from."""


@refs_app.command("generate")
def refs_generate_command(
    out: Annotated[Path, typer.Option("--out", help="Destination folder for ref_XX.npy (rad, 20 Hz).")],
    n: Annotated[int, typer.Option("--n", help="Number of references.")] = 40,
    seed: Annotated[int, typer.Option("--seed", help="Random seed.")] = 0,
    preset_name: Annotated[str, typer.Option("--preset", help="Cycle generator preset (xe75).")] = "xe75",
    home: Annotated[
        str | None,
        typer.Option(
            "--home",
            help="'q_boom,q_arm,q_bucket,q_swing' rad: every reference starts and ends at this pose (a slow move in and "
            "out), so a machine stands at each next start.",
        ),
    ] = None,
    force: Annotated[
        bool,
        typer.Option(
            "--force",
            help="Write into a non-empty OUT: first delete its reference files (*.npy, *.csv) and references.png, "
            "which would be read along with the new ones; other files are kept.",
        ),
    ] = False,
) -> None:
    """Draw operator-like loading cycles (15–25 s at 20 Hz) and write them as ref_XX.npy."""
    from efficienttrack.core.angles import parse_pose
    from efficienttrack.data.cycles import generate_references, homed
    from efficienttrack.data.references import SUFFIXES, save_references

    check_output_folder(out)
    refs = generate_references(n, seed, preset_name)
    if home is not None:
        refs = homed(refs, parse_pose(home, "--home"))
    prepare_output_folder(out, (*(f"*{suffix}" for suffix in SUFFIXES), REFERENCES_PLOT), force)
    save_references(refs, out)
    durations = [ref.duration for ref in refs]
    typer.echo(f"wrote {len(refs)} references to {out} ({min(durations):.1f}–{max(durations):.1f} s)")


@refs_app.command("plot")
def refs_plot_command(
    source: Annotated[Path, typer.Argument(help="Folder (or file) of references (.npy/.csv, rad).")],
    out: Annotated[Path | None, typer.Option("--out", help="PNG to write; default SOURCE/references.png.")] = None,
) -> None:
    """Draw all references per joint, in degrees against time."""
    from efficienttrack.data.references import load_references
    from efficienttrack.workflow.plots import plot_references

    path = check_output_file(out or (source if source.is_dir() else source.parent) / REFERENCES_PLOT)
    refs = load_references(source)
    typer.echo(f"plotted {len(refs)} references to {plot_references(refs, path)}")


@app.command("metrics")
def metrics_command(
    paths: Annotated[list[Path], typer.Argument(help="Episode files or folders (.npz, our .csv, upstream .npy/.csv).")],
    json_output: Annotated[bool, typer.Option("--json", help='One JSON object per row and line, with a "path".')] = False,
    pool: Annotated[bool, typer.Option("--pool", help="One row for all the episodes of all PATHs.")] = False,
    per_episode: Annotated[bool, typer.Option("--per-episode", help="One row per episode file.")] = False,
    csv_file: Annotated[Path | None, typer.Option("--csv", help="Also write the rows to this CSV file.")] = None,
    recursive: RecursiveOpt = False,
) -> None:
    """Tracking metrics (the paper's definitions, per episode, averaged over episodes): one row per PATH.

    A folder means the episodes directly in it (--recursive for its subfolders too).
    """
    if pool and per_episode:
        raise EfficientTrackError("metrics: --pool and --per-episode exclude each other")
    if csv_file is not None:
        check_output_file(csv_file, "--csv")
    rows = metrics_by_path(paths, recursive=recursive, pool=pool, per_episode=per_episode)
    if csv_file is not None:
        write_metrics_csv(rows, csv_file)
    if json_output:
        for name, result in rows.items():
            typer.echo(json.dumps(finite_json({"path": name, **rounded(result)}, "metrics"), allow_nan=False))
    else:
        wide_console(max(map(len, rows))).print(metrics_table(rows, title="Tracking metrics", label="path"))


@app.command("convert")
def convert_command(
    ctx: typer.Context,
    paths: Annotated[
        list[Path],
        typer.Argument(
            help="Episode files or folders (.npz, our .csv, upstream .npy/.csv), deploy tick logs (.jsonl), or tables "
            "with a time column (.csv, .parquet) to resample onto the 20 Hz grid (docs/your-logs.md)."
        ),
    ],
    out: Annotated[Path, typer.Option("--out", help="Destination folder; files are named after the episodes.")],
    fmt: Annotated[str, typer.Option("--format", help="Output format: npz or csv.")] = "npz",
    recursive: RecursiveOpt = False,
    force: Annotated[
        bool,
        typer.Option(
            "--force",
            help="Write into a non-empty OUT: first delete its episode files (*.npz, *.npy, *.csv), which would be read "
            "along with the new ones; other files are kept.",
        ),
    ] = False,
    column: Annotated[
        list[str] | None,
        typer.Option(
            "--column",
            help="Table column of a channel, FIELD.JOINT=COLUMN (q.boom=BoomAngle) or a field's four, FIELD=C1,C2,C3,C4 "
            "in joint order; FIELD: q, qd, q_ref, q_des, u (repeatable; default names q_boom, ...). Imports every "
            ".csv/.parquet.",
        ),
    ] = None,
    time_column: Annotated[
        str | None, typer.Option("--time-column", help="Table column of the sample times (default t). Imports every table.")
    ] = None,
    time_unit: Annotated[
        str | None, typer.Option("--time-unit", help="Unit of the time column: s (default), ms, us, ns. Imports every table.")
    ] = None,
    angle_unit: Annotated[
        str | None,
        typer.Option(
            "--angle-unit", help="Unit of the table's angles: rad (default) or deg (qd in °/s). Imports every table."
        ),
    ] = None,
    max_gap: Annotated[
        float | None,
        typer.Option("--max-gap", help=f"Longest gap between two samples of a table, s (default {MAX_GAP})."),
    ] = None,
) -> None:
    """Convert episode records between formats (upstream .npy/.csv → .npz, .npz ↔ .csv; a deploy log .jsonl → records).

    A table (.parquet, or a .csv that is not one of our records) is imported: its columns mapped to the channels, resampled
    onto the 20 Hz grid, velocities estimated when it has none (docs/your-logs.md). --column, --time-column, --time-unit
    or --angle-unit import every .csv given, ours too.
    """
    from efficienttrack.deploy.deployment import records_from_log

    check_output_folder(out)
    gap = MAX_GAP if max_gap is None else max_gap
    check_options(column, time_unit or "s", angle_unit or "rad", gap)  # before any file is read, tables or not
    import_all = bool(column) or any(option is not None for option in (time_column, time_unit, angle_unit))
    logs = [path for path in paths if path.suffix == ".jsonl" and path.is_file()]
    files = [file for path in paths if path not in logs for file in _convert_inputs(path, recursive)]
    inside = [file for file in files if file.resolve().parent == out.resolve()]
    if inside:
        raise EfficientTrackError(f"--out {out}: holds the input {inside[0].name}; write the converted episodes elsewhere")
    records = []
    for log in logs:
        found = records_from_log(log)
        if not found:
            raise EfficientTrackError(f"{log}: no episode records in this tick log (no two usable ticks in a row)")
        records += found
    for file in files:
        table = file.suffix in TABLE_SUFFIXES and (import_all or needs_import(file))
        if table:
            records.append(read_table(file, column, time_column or "t", time_unit or "s", angle_unit or "rad", gap))
        else:
            records.append(load_record(file))
    _lock(ctx, out, resumable=False)  # after the inputs were read: a refused conversion leaves no folder behind
    prepare_output_folder(out, tuple(f"*{suffix}" for suffix in RECORD_SUFFIXES), force)
    written = save_records(records, out, fmt)
    typer.echo(f"wrote {len(written)} episode(s) to {out}")


def _convert_inputs(path: Path, recursive: bool) -> list[Path]:
    """The files ``convert`` reads for ``path``: itself, or a folder's episode files (:func:`record_files`) and tables."""
    if not path.is_dir():
        return record_files(path, recursive)
    tables = sorted(p for p in (path.rglob("*.parquet") if recursive else path.glob("*.parquet")) if p.is_file())
    return sorted([*find_record_files(path, recursive), *tables]) or record_files(path, recursive)


@app.command("import-rosbag")
def import_rosbag_command(
    ctx: typer.Context,
    bags: Annotated[list[Path], typer.Argument(help="rosbag2 folders (metadata.yaml + .db3/.mcap), one episode each.")],
    out: Annotated[Path, typer.Option("--out", help="Destination folder; episodes are named after the bag folders.")],
    reference: Annotated[
        str,
        typer.Option(
            "--reference", help="Topic of the references sent (Float64MultiArray, JointState or JointTrajectory) → q_ref."
        ),
    ],
    desired: Annotated[
        str | None, typer.Option("--desired", help="Topic of the desired positions → q_des (default: q_des = q_ref).")
    ] = None,
    joint_states: Annotated[str, typer.Option("--joint-states", help="JointState topic → q, qd.")] = "/joint_states",
    joint: Annotated[
        list[str] | None, typer.Option("--joint", help="JOINT=ROS_NAME, e.g. boom=boom_joint (repeatable; see docs/ros2.md).")
    ] = None,
    clock: Annotated[
        str, typer.Option("--clock", help="JointState/JointTrajectory stamps: header (header.stamp) or bag (receive time).")
    ] = "header",
    max_gap: Annotated[float, typer.Option("--max-gap", help="Longest gap between two messages of a topic, s.")] = 0.25,
    fmt: Annotated[str, typer.Option("--format", help="Output format: npz or csv.")] = "npz",
    force: Annotated[
        bool, typer.Option("--force", help="Write into a non-empty OUT: first delete its episode files.")
    ] = False,
) -> None:
    """Import ROS 2 logs (rosbag2) as episode records on the 20 Hz grid, without ROS (docs/ros2.md)."""
    from efficienttrack.data.rosbag import read_rosbag

    check_output_folder(out)
    records = [read_rosbag(bag, reference, desired, joint_states, joint, clock, max_gap) for bag in bags]
    _lock(ctx, out, resumable=False)  # after the bags were read: a refused import leaves no folder behind
    prepare_output_folder(out, tuple(f"*{suffix}" for suffix in RECORD_SUFFIXES), force)
    written = save_records(records, out, fmt)
    typer.echo(f"wrote {len(written)} episode(s), {sum(map(len, records))} steps at 20 Hz, to {out}")


@app.command("collect")
def collect_command(
    ctx: typer.Context,
    refs: Annotated[Path, typer.Option("--refs", help="Folder of reference trajectories (.npy/.csv, rad).")],
    out: Annotated[Path, typer.Option("--out", help="Output folder (pass_<k>/ records; an interrupted run resumes).")],
    system: SystemOpt = None,
    plant: PlantOpt = None,
    pd: PdOpt = None,
    system_opt: SystemOpts = None,
    limits: LimitsOpt = None,
    machine: MachineOpt = None,
    machine_opt: MachineOpts = None,
    between_episodes: BetweenOpt = "approach",
    loop: Annotated[
        bool,
        typer.Option("--loop", help="Drive the simulator through the fixed-rate loop, one episode at a time, as --machine."),
    ] = False,
    arm: ArmOpt = False,
    fast: FastOpt = False,
    passes: Annotated[int, typer.Option("--passes", help="Passes over the references.")] = COLLECT.passes,
    noise_ratio: Annotated[str, typer.Option("--noise-ratio", help="Noisy:clean episodes.")] = COLLECT.noise_ratio_text,
    sigma_max: Annotated[float, typer.Option("--sigma-max", help="Largest noise level σ_max, rad.")] = COLLECT.sigma_max,
    noise_rho: Annotated[
        float, typer.Option("--noise-rho", help="Correlation of consecutive noise steps, AR(1) (0: white, the paper's).")
    ] = COLLECT.noise_rho,
    seed: Annotated[int, typer.Option("--seed", help="Noise seed.")] = COLLECT.seed,
) -> None:
    """Algorithm 1: track the references with the position controller, with and without noise, and record it.

    On a machine (--machine, with --limits and --arm) every episode runs through the loop that deploy runs:
    deadlines, watchdogs, no noise at the first tick and none at the end, the noise's change per tick limited by the
    limits' max_adjust_rate, a tick log per episode in OUT/logs/. --loop runs the simulator the same way.
    """
    from efficienttrack.data.references import load_references
    from efficienttrack.workflow.collect import LoopMachine, collect

    check_output_folder(out)
    ratio = CollectConfig.parse_noise_ratio(noise_ratio)
    cfg = CollectConfig(sigma_max=sigma_max, noise_ratio=ratio, noise_rho=noise_rho, passes=passes, seed=seed)
    spec = _system_spec(system, plant, pd, system_opt, limits)
    references = load_references(refs)
    looped = loop or machine is not None
    if fast and not looped:
        raise EfficientTrackError("--fast sets the clock of the loop: add --loop (the simulator) or leave --fast out")
    if looped and not arm:
        raise EfficientTrackError(
            "collect through the loop sends references to the machine: add --arm to allow motion "
            "(the noise is an adjustment within the limits' max_adjust, ramped in and out)"
        )
    if looped:
        from efficienttrack.deploy.deployment import machine_parts

        options = parse_options(machine_opt, "--machine-opt")
        make_machine, machine_limits, clock = machine_parts(spec, machine, options, fast)
        simulator = f"simulator {spec.plant or spec.system_name}"
        driven = LoopMachine(make_machine, machine_limits, clock, machine or simulator, between=between(between_episodes))
    _lock(ctx, out)
    result = collect(driven if looped else spec.open(), references, cfg, out)
    typer.echo(
        f"collected {len(result.records)} episodes, {result.interaction_steps} interaction steps "
        f"({result.resumed_passes} pass(es) resumed) into {out}"
    )

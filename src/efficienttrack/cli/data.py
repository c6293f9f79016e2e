"""Commands on references and episode data: ``refs generate``/``refs plot``, ``metrics``, ``convert``, ``collect``."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from efficienttrack.cli.common import (
    PdOpt,
    PlantOpt,
    RecursiveOpt,
    SystemOpt,
    SystemOpts,
    _lock,
    _system_spec,
    app,
    wide_console,
)
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import check_output_file, check_output_folder, finite_json, prepare_output_folder
from efficienttrack.data.metrics import metrics_by_path, metrics_table, rounded, write_metrics_csv
from efficienttrack.data.records import RECORD_SUFFIXES, load_records, record_files, save_records
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
    from efficienttrack.data.cycles import generate_references
    from efficienttrack.data.references import SUFFIXES, save_references

    check_output_folder(out)
    refs = generate_references(n, seed, preset_name)
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
        typer.Argument(help="Episode files or folders (.npz, our .csv, upstream .npy/.csv), or deploy tick logs (.jsonl)."),
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
) -> None:
    """Convert episode records between formats (upstream .npy/.csv → .npz, .npz ↔ .csv; a deploy log .jsonl → records)."""
    from efficienttrack.deploy.deployment import records_from_log

    check_output_folder(out)
    logs = [path for path in paths if path.suffix == ".jsonl" and path.is_file()]
    files = [file for path in paths if path not in logs for file in record_files(path, recursive)]
    inside = [file for file in files if file.resolve().parent == out.resolve()]
    if inside:
        raise EfficientTrackError(f"--out {out}: holds the input {inside[0].name}; write the converted episodes elsewhere")
    records = []
    for log in logs:
        found = records_from_log(log)
        if not found:
            raise EfficientTrackError(f"{log}: no episode records in this tick log (no two usable ticks in a row)")
        records += found
    records += load_records(files) if files else []
    _lock(ctx, out)  # after the inputs were read: a refused conversion leaves no folder behind
    prepare_output_folder(out, tuple(f"*{suffix}" for suffix in RECORD_SUFFIXES), force)
    written = save_records(records, out, fmt)
    typer.echo(f"wrote {len(written)} episode(s) to {out}")


@app.command("import-rosbag")
def import_rosbag_command(
    ctx: typer.Context,
    bags: Annotated[list[Path], typer.Argument(help="rosbag2 folders (metadata.yaml + .db3/.mcap), one episode each.")],
    out: Annotated[Path, typer.Option("--out", help="Destination folder; episodes are named after the bag folders.")],
    reference: Annotated[
        str, typer.Option("--reference", help="Topic of the references sent (Float64MultiArray or JointState) → q_ref.")
    ],
    desired: Annotated[
        str | None, typer.Option("--desired", help="Topic of the desired positions → q_des (default: q_des = q_ref).")
    ] = None,
    joint_states: Annotated[str, typer.Option("--joint-states", help="JointState topic → q, qd.")] = "/joint_states",
    joint: Annotated[
        list[str] | None, typer.Option("--joint", help="JOINT=ROS_NAME, e.g. boom=boom_joint (repeatable; see docs/ros2.md).")
    ] = None,
    clock: Annotated[str, typer.Option("--clock", help="JointState stamps: header (header.stamp) or bag (receive time).")] = (
        "header"
    ),
    max_gap: Annotated[float, typer.Option("--max-gap", help="Longest gap between two messages of a topic, s.")] = 0.25,
    fmt: Annotated[str, typer.Option("--format", help="Output format: npz or csv.")] = "npz",
    force: Annotated[
        bool, typer.Option("--force", help="Write into a non-empty OUT: first delete its episode files.")
    ] = False,
) -> None:
    """Import ROS 2 logs (rosbag2) as episode records on the 20 Hz grid, without ROS (docs/ros2.md)."""
    from efficienttrack.data.rosbag import read_rosbag

    check_output_folder(out)
    options = {"desired": desired, "joint_states": joint_states, "joints": joint, "clock": clock, "max_gap": max_gap}
    records = [read_rosbag(bag, reference, **options) for bag in bags]
    _lock(ctx, out)  # after the bags were read: a refused import leaves no folder behind
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
    passes: Annotated[int, typer.Option("--passes", help="Passes over the references.")] = COLLECT.passes,
    noise_ratio: Annotated[str, typer.Option("--noise-ratio", help="Noisy:clean episodes.")] = COLLECT.noise_ratio_text,
    sigma_max: Annotated[float, typer.Option("--sigma-max", help="Largest noise level σ_max, rad.")] = COLLECT.sigma_max,
    seed: Annotated[int, typer.Option("--seed", help="Noise seed.")] = COLLECT.seed,
) -> None:
    """Algorithm 1: track the references with the position controller, with and without noise, and record it."""
    from efficienttrack.data.references import load_references
    from efficienttrack.workflow.collect import collect

    check_output_folder(out)
    ratio = CollectConfig.parse_noise_ratio(noise_ratio)
    cfg = CollectConfig(sigma_max=sigma_max, noise_ratio=ratio, passes=passes, seed=seed)
    spec = _system_spec(system, plant, pd, system_opt)
    references = load_references(refs)
    _lock(ctx, out)
    result = collect(spec.open(), references, cfg, out)
    typer.echo(
        f"collected {len(result.records)} episodes, {result.interaction_steps} interaction steps "
        f"({result.resumed_passes} pass(es) resumed) into {out}"
    )

"""The ``efficienttrack`` command line: every subcommand is a thin wrapper over a library function."""

from __future__ import annotations

import json
import math
import sys
import warnings
from dataclasses import replace
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

import efficienttrack
from efficienttrack.collect import CollectConfig
from efficienttrack.config import ROUND_DATA, RunConfig
from efficienttrack.errors import EfficientTrackError
from efficienttrack.fileio import (
    check_output_file,
    check_output_folder,
    finite_json,
    os_error_text,
    output_lock,
    prepare_output_folder,
)
from efficienttrack.loop import LoopConfig
from efficienttrack.metrics import metrics_by_path, metrics_table, rounded, write_metrics_csv
from efficienttrack.records import RECORD_SUFFIXES, load_records, record_files, save_records
from efficienttrack.systems.fit import FitConfig

TABLE_WIDTH = 132
"""Characters the columns of a metrics table take besides its row labels."""

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


def parse_options(pairs: list[str] | None, flag: str = "--system-opt") -> dict[str, object]:
    """Turn repeated ``key=value`` strings into keyword options (numbers and booleans parsed).

    Args:
        pairs: the ``key=value`` strings as given on the command line (``None`` when the option was not used).
        flag: the option's name, used in error messages.

    Returns:
        ``{key: value}``, each value an int, float or bool where it parses as one, else the string.

    Raises:
        EfficientTrackError: a string without ``=`` or with an empty key.
    """
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


def _lock(ctx: typer.Context, out: Path, folder: bool = True) -> None:
    """Hold the lock of output ``out`` (a folder, else a checkpoint) until the command ``ctx`` ends, however it ends."""
    ctx.with_resource(output_lock(out, folder=folder))


REFERENCES_PLOT = "references.png"
"""Default name of the plot ``refs plot`` draws next to the references."""
RecursiveOpt = Annotated[
    bool, typer.Option("--recursive", "-r", help="Read subfolders too (a folder alone means the episodes directly in it).")
]


def wide_console(label_width: int = 8) -> Console:
    """A console wide enough for a metrics table whose row labels are ``label_width`` characters long.

    Figures are never cropped or folded, also on a narrow terminal or when the output is not a terminal.

    Args:
        label_width: length of the longest row label (a method name or a path).
    """
    return Console(width=max(Console().width, TABLE_WIDTH + label_width))


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
    from efficienttrack.cycles import generate_references
    from efficienttrack.references import SUFFIXES, save_references

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
    from efficienttrack.plots import plot_references
    from efficienttrack.references import load_references

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
    paths: Annotated[list[Path], typer.Argument(help="Episode files or folders (.npz, our .csv, upstream .npy/.csv).")],
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
    """Convert episode records between formats (upstream .npy/.csv → .npz, .npz ↔ .csv)."""
    check_output_folder(out)
    files = [file for path in paths for file in record_files(path, recursive)]
    inside = [file for file in files if file.resolve().parent == out.resolve()]
    if inside:
        raise EfficientTrackError(f"--out {out}: holds the input {inside[0].name}; write the converted episodes elsewhere")
    records = load_records(files)
    prepare_output_folder(out, tuple(f"*{suffix}" for suffix in RECORD_SUFFIXES), force)
    written = save_records(records, out, fmt)
    typer.echo(f"wrote {len(written)} episode(s) to {out}")


@app.command("import-rosbag")
def import_rosbag_command(
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
    from efficienttrack.rosbag import read_rosbag

    check_output_folder(out)
    options = {"desired": desired, "joint_states": joint_states, "joints": joint, "clock": clock, "max_gap": max_gap}
    records = [read_rosbag(bag, reference, **options) for bag in bags]
    prepare_output_folder(out, tuple(f"*{suffix}" for suffix in RECORD_SUFFIXES), force)
    written = save_records(records, out, fmt)
    typer.echo(f"wrote {len(written)} episode(s), {sum(map(len, records))} steps at 20 Hz, to {out}")


SystemOpt = Annotated[
    str | None,
    typer.Option(
        "--system",
        help="Closed-loop system: built-in name (xe75; learned with --system-opt model=CKPT) or module.path:callable.",
    ),
]
PlantOpt = Annotated[
    str | None, typer.Option("--plant", help="Plant (PWM level) wrapped with the PD controller: xe75 or module.path:callable.")
]
PdOpt = Annotated[str, typer.Option("--pd", help="PD gains for --plant: preset name (xe75) or a JSON file.")]
SystemOpts = Annotated[list[str] | None, typer.Option("--system-opt", help="key=value option of the system (repeatable).")]
LimitsOpt = Annotated[
    Path | None,
    typer.Option("--limits", help="YAML/JSON of the guard's joint limits and adjustment bounds (amends the system's)."),
]


def _system_spec(system: str | None, plant: str | None, pd: str, options: list[str] | None, limits: Path | None = None):
    from efficienttrack.systems.spec import SystemSpec

    return SystemSpec(
        system=system,
        plant=plant,
        pd=pd,
        options=tuple(parse_options(options).items()),
        limits=None if limits is None else str(limits),
    )


def _run_config(
    config: Path | None,
    preset_name: str,
    seed: int | None,
    device: str | None,
    rounds: int | None = None,
    round_data: str | None = None,
):
    from efficienttrack.config import load_config, preset, with_overrides

    if round_data is not None and round_data not in ROUND_DATA:
        raise EfficientTrackError(f"--round-data '{round_data}': expected one of {', '.join(ROUND_DATA)}")
    base = load_config(config, preset(preset_name)) if config is not None else preset(preset_name)
    return with_overrides(base, seed=seed, device=device, rounds=rounds, round_data=round_data)


RoundsOpt = Annotated[
    int | None,
    typer.Option(
        "--rounds", min=1, help="Continual-learning rounds (default: the config's, 1): deploy, record, retrain, repeat."
    ),
]
RoundDataOpt = Annotated[
    str | None,
    typer.Option(
        "--round-data",
        help="What later rounds train on: all (every episode so far) or new (default: all).",
    ),
]


COLLECT = CollectConfig()
"""Where the ``collect`` options take their defaults from."""


@app.command("collect")
def collect_command(
    ctx: typer.Context,
    refs: Annotated[Path, typer.Option("--refs", help="Folder of reference trajectories (.npy/.csv, rad).")],
    out: Annotated[Path, typer.Option("--out", help="Output folder (pass_<k>/ records; an interrupted run resumes).")],
    system: SystemOpt = None,
    plant: PlantOpt = None,
    pd: PdOpt = "xe75",
    system_opt: SystemOpts = None,
    passes: Annotated[int, typer.Option("--passes", help="Passes over the references.")] = COLLECT.passes,
    noise_ratio: Annotated[str, typer.Option("--noise-ratio", help="Noisy:clean episodes.")] = COLLECT.noise_ratio_text,
    sigma_max: Annotated[float, typer.Option("--sigma-max", help="Largest noise level σ_max, rad.")] = COLLECT.sigma_max,
    seed: Annotated[int, typer.Option("--seed", help="Noise seed.")] = COLLECT.seed,
) -> None:
    """Algorithm 1: track the references with the position controller, with and without noise, and record it."""
    from efficienttrack.collect import collect
    from efficienttrack.references import load_references

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


DeviceOpt = Annotated[str, typer.Option("--device", help="auto, cpu or cuda.")]
PlotsOpt = Annotated[
    int | None, typer.Option("--plots", help="Draw tracking plots of the first N test references (default: every one).")
]
TrainSeedOpt = Annotated[int, typer.Option("--seed", help="Seed of initialization and window sampling.")]


@app.command("evaluate")
def evaluate_command(
    ctx: typer.Context,
    refs: Annotated[Path, typer.Option("--refs", help="Folder of reference trajectories (.npy/.csv, rad).")],
    out: Annotated[Path, typer.Option("--out", help="Output folder: records/, metrics.json, plots/, run.log.")],
    system: SystemOpt = None,
    plant: PlantOpt = None,
    pd: PdOpt = "xe75",
    system_opt: SystemOpts = None,
    limits: LimitsOpt = None,
    policy: Annotated[
        Path | None, typer.Option("--policy", help="Policy checkpoint (policy.pt) to compare with PD; PD alone without.")
    ] = None,
    device: DeviceOpt = "auto",
    plots: PlotsOpt = None,
    force: Annotated[
        bool,
        typer.Option("--force", help="Write into a non-empty OUT: first delete an earlier evaluation's outputs there."),
    ] = False,
) -> None:
    """Algorithm 2: track the references with PD alone and with the adjustment policy; metrics and plots as `run`.

    An interrupted evaluation (or one whose system failed) resumes with the episodes not yet recorded.
    """
    from efficienttrack.pipeline import EVALUATE_JSON, EVALUATE_OUTPUTS, evaluate
    from efficienttrack.references import load_references

    check_output_folder(out)
    spec, references = _system_spec(system, plant, pd, system_opt, limits), load_references(refs)
    _lock(ctx, out)
    interrupted = (out / EVALUATE_JSON).exists() and not (out / "metrics.json").exists()
    if force or not interrupted:
        prepare_output_folder(out, EVALUATE_OUTPUTS, force)
    evaluate(spec, references, out, policy, device, wide_console(), plots)


ThreadsOpt = Annotated[
    int,
    typer.Option("--threads", help="torch CPU threads (1: fastest for cpu-preset networks on 2 shared cores; 0: default)."),
]


def _set_threads(threads: int) -> None:
    import torch

    if threads < 0:
        raise EfficientTrackError(f"--threads {threads}: expected ≥ 0")
    if threads:
        torch.set_num_threads(threads)


RunForceOpt = Annotated[
    bool,
    typer.Option(
        "--force",
        help="Start afresh: delete the earlier run's outputs in OUT (records, checkpoints and training states, model, "
        "policy, metrics, plots; other files are kept) instead of resuming it or refusing other settings.",
    ),
]
PresetOpt = Annotated[str, typer.Option("--preset", help="Settings preset: paper, cpu or tiny.")]
ConfigOpt = Annotated[Path | None, typer.Option("--config", help="YAML/JSON overriding preset fields.")]
RunSeedOpt = Annotated[int | None, typer.Option("--seed", help="Seed of collection noise and training.")]
RunDeviceOpt = Annotated[str | None, typer.Option("--device", help="auto, cpu or cuda.")]


def _prepare_run_folder(out: Path, outputs: tuple[str, ...], force: bool) -> None:
    """With ``force`` delete the run's ``outputs`` in OUT; else refuse an OUT holding other files and no run to resume."""
    resumable = (out / "run.json").exists() or not out.is_dir() or all(entry.name in outputs for entry in out.iterdir())
    if force or not resumable:
        prepare_output_folder(out, outputs, force)


@app.command("run")
def run_command(
    ctx: typer.Context,
    train_refs: Annotated[Path, typer.Option("--train-refs", help="Folder of training references.")],
    test_refs: Annotated[Path, typer.Option("--test-refs", help="Folder of held-out test references.")],
    out: Annotated[Path, typer.Option("--out", help="Output folder; rerunning resumes where it stopped.")],
    system: SystemOpt = None,
    plant: PlantOpt = None,
    pd: PdOpt = "xe75",
    system_opt: SystemOpts = None,
    limits: LimitsOpt = None,
    preset_name: PresetOpt = "cpu",
    config: ConfigOpt = None,
    seed: RunSeedOpt = None,
    device: RunDeviceOpt = None,
    rounds: RoundsOpt = None,
    round_data: RoundDataOpt = None,
    threads: ThreadsOpt = 1,
    plots: PlotsOpt = None,
    force: RunForceOpt = False,
) -> None:
    """The whole method: collect, train model and policy, evaluate PD alone vs EfficientTrack on the test references."""
    from efficienttrack.pipeline import RUN_OUTPUTS, run_pipeline
    from efficienttrack.references import load_references

    check_output_folder(out)
    _set_threads(threads)
    spec = _system_spec(system, plant, pd, system_opt, limits)
    cfg = _run_config(config, preset_name, seed, device, rounds, round_data)
    train, test = load_references(train_refs), load_references(test_refs)
    _lock(ctx, out)
    _prepare_run_folder(out, RUN_OUTPUTS, force)
    run_pipeline(spec, train, test, out, cfg, wide_console(), plots)


@app.command("demo")
def demo_command(
    ctx: typer.Context,
    out: Annotated[Path, typer.Option("--out", help="Output folder; rerunning resumes where it stopped.")] = Path("runs/demo"),
    preset_name: PresetOpt = "cpu",
    config: ConfigOpt = None,
    seed: RunSeedOpt = None,
    device: RunDeviceOpt = None,
    rounds: RoundsOpt = None,
    round_data: RoundDataOpt = None,
    threads: ThreadsOpt = 1,
    plots: PlotsOpt = None,
    force: RunForceOpt = False,
) -> None:
    """The whole method on the built-in xe75 simulator with generated references (32 train / 8 test)."""
    from efficienttrack.pipeline import DEMO_OUTPUTS, demo

    check_output_folder(out)
    _set_threads(threads)
    cfg = _run_config(config, preset_name, seed, device, rounds, round_data)
    _lock(ctx, out)
    _prepare_run_folder(out, DEMO_OUTPUTS, force)
    demo(out, cfg, console=wide_console(), max_plots=plots)


DataOpt = Annotated[
    list[Path], typer.Option("--data", help="Episode files or folders (repeatable; a folder's own episodes, see --recursive).")
]
TrainForceOpt = Annotated[
    bool, typer.Option("--force", help="Start afresh: delete the training state (OUT with .state.pt) instead of resuming it.")
]


def _check_checkpoint(out: Path) -> None:
    """Check that checkpoint ``out`` (a ``.pt``) and its log folder (``OUT`` with ``.logs``) can be written."""
    from efficienttrack.training import check_checkpoint_path

    check_output_file(out)
    check_checkpoint_path(out)
    check_output_folder(out.with_suffix(".logs"))


def _training_state(out: Path, force: bool) -> Path:
    """The training-state file next to checkpoint ``out``, deleted first when ``force``."""
    state = out.with_suffix(".state.pt")
    if force:
        state.unlink(missing_ok=True)
    return state


LearnPresetOpt = Annotated[str, typer.Option("--preset", help="Training preset: paper (GPU), cpu or tiny.")]
StepsOpt = Annotated[int | None, typer.Option("--steps", help="Override the preset's number of optimizer steps.")]
HeldOutOpt = Annotated[
    list[Path] | None,
    typer.Option("--held-out", help="Episodes not trained on, for the held-out figure in the logs (repeatable)."),
]


def _learn_preset(presets: dict, name: str, steps: int | None, share: float = 1.0):
    """The preset's config, with ``steps`` optimizer steps when given, else its own scaled by ``share``."""
    import dataclasses

    if name not in presets:
        raise EfficientTrackError(f"--preset '{name}': expected one of {', '.join(presets)}")
    return presets[name].scaled(share) if steps is None else dataclasses.replace(presets[name], steps=steps, epochs=None)


def _warm_start(option: str, path: Path | None, load, cfg, device: str):
    """Load the checkpoint given to ``option`` (None: a cold start) and the config to continue it with.

    Returns ``(network or None, config)``: the network's own sizes and loss, the schedule of ``cfg`` (the preset).
    """
    from efficienttrack.next_round import continued_config

    if path is None:
        return None, cfg
    try:
        network = load(path, device)
    except EfficientTrackError as exc:
        raise EfficientTrackError(f"{option}: {exc}") from exc
    typer.echo(f"warm start from {path}: its sizes ({network.cfg.hidden}×{network.cfg.layers}), the preset's schedule")
    return network, continued_config(cfg, network.cfg)


InitModelOpt = Annotated[
    Path | None,
    typer.Option(
        "--init-model",
        help="Start from this model checkpoint (weights and scaling; its sizes, the preset's schedule): a round's warm start.",
    ),
]
InitPolicyOpt = Annotated[
    Path | None,
    typer.Option(
        "--init-policy",
        help="Start from this policy checkpoint (weights, scaling; its sizes, the preset's schedule): a round's warm start.",
    ),
]


@app.command("train-model")
def train_model_command(
    ctx: typer.Context,
    data: DataOpt,
    out: Annotated[
        Path, typer.Option("--out", help="Model checkpoint (model.pt; config to model.json, scalar logs to model.logs/).")
    ],
    preset_name: LearnPresetOpt = "cpu",
    steps: StepsOpt = None,
    held_out: HeldOutOpt = None,
    init_model: InitModelOpt = None,
    device: DeviceOpt = "auto",
    seed: TrainSeedOpt = 0,
    threads: ThreadsOpt = 1,
    recursive: RecursiveOpt = False,
    force: TrainForceOpt = False,
) -> None:
    """Train the closed-loop dynamics model on records (multi-step BPTT); an interrupted run resumes."""
    from efficienttrack.dynamics import MODEL_PRESETS, load_model, save_model, train_model

    _check_checkpoint(out)
    _set_threads(threads)
    init, cfg = _warm_start("--init-model", init_model, load_model, _learn_preset(MODEL_PRESETS, preset_name, steps), device)
    records, held = load_records(data, recursive), load_records(held_out, recursive) if held_out else []
    logs = out.with_suffix(".logs")
    _lock(ctx, out, folder=False)
    result = train_model(cfg, records, device, seed, True, _training_state(out, force), logs, held, init)
    save_model(result.model, out, result.fingerprint)
    typer.echo(
        f"trained model on {result.windows} windows ({sum(map(len, records))} steps), {result.steps} steps in "
        f"{result.seconds:.0f} s, final loss {result.losses[-1]:.4g}; saved {out}, logs in {logs}"
    )


@app.command("model-error")
def model_error_command(
    model: Annotated[Path, typer.Option("--model", help="Model checkpoint (model.pt).")],
    data: DataOpt,
    steps: Annotated[int, typer.Option("--steps", help="Prediction horizon.")] = 20,
    device: DeviceOpt = "auto",
    json_output: Annotated[bool, typer.Option("--json", help="Print one JSON line.")] = False,
    threads: ThreadsOpt = 1,
    recursive: RecursiveOpt = False,
) -> None:
    """Multi-step model prediction error (MPE, the paper's Tr.MPE/Te.MPE) on records, degrees."""
    from efficienttrack.dynamics import load_model, model_error

    _set_threads(threads)
    result = model_error(load_model(model, device), load_records(data, recursive), steps)
    if json_output:
        typer.echo(json.dumps(finite_json(result._asdict(), "model-error"), allow_nan=False))
        return
    joints = ", ".join(f"{v:.3f}" for v in result.per_joint_deg)
    typer.echo(f"MPE {result.mpe_deg:.3f}° over {result.windows} windows × {steps} steps; per joint {joints}°")


@app.command("train-policy")
def train_policy_command(
    ctx: typer.Context,
    model: Annotated[Path, typer.Option("--model", help="Model checkpoint (model.pt) to train through.")],
    data: DataOpt,
    out: Annotated[
        Path, typer.Option("--out", help="Policy checkpoint (policy.pt; config to policy.json, scalar logs to policy.logs/).")
    ],
    preset_name: LearnPresetOpt = "cpu",
    steps: StepsOpt = None,
    held_out: HeldOutOpt = None,
    init_policy: InitPolicyOpt = None,
    device: DeviceOpt = "auto",
    seed: TrainSeedOpt = 0,
    threads: ThreadsOpt = 1,
    recursive: RecursiveOpt = False,
    force: TrainForceOpt = False,
) -> None:
    """Train the adjustment policy through the frozen model (multi-step BPTT); an interrupted run resumes."""
    from efficienttrack.dynamics import load_model
    from efficienttrack.policy import POLICY_PRESETS, load_policy, predicted_tracking_error, save_policy, train_policy

    _check_checkpoint(out)
    _set_threads(threads)
    preset_cfg = _learn_preset(POLICY_PRESETS, preset_name, steps)
    init, cfg = _warm_start("--init-policy", init_policy, load_policy, preset_cfg, device)
    g_theta, records = load_model(model, device), load_records(data, recursive)
    held, logs = load_records(held_out, recursive) if held_out else [], out.with_suffix(".logs")
    _lock(ctx, out, folder=False)
    result = train_policy(cfg, g_theta, records, device, seed, True, _training_state(out, force), logs, held, init)
    save_policy(result.policy, out, result.fingerprint)
    before = predicted_tracking_error(g_theta, records, None, cfg.rollout_length)
    after = predicted_tracking_error(g_theta, records, result.policy, cfg.rollout_length)
    typer.echo(
        f"trained policy, {result.steps} steps in {result.seconds:.0f} s; model-predicted tracking error "
        f"{before.mae_deg:.3f}° (a = 0) → {after.mae_deg:.3f}°; saved {out}, logs in {logs}"
    )


@app.command("export")
def export_command(
    ctx: typer.Context,
    policy: Annotated[Path, typer.Option("--policy", help="Policy checkpoint (policy.pt) to export.")],
    out: Annotated[Path, typer.Option("--out", help="Export folder: policy.onnx and its contract policy.json.")],
    force: Annotated[bool, typer.Option("--force", help="Replace an earlier export in OUT (other files are kept).")] = False,
) -> None:
    """Export a trained policy to ONNX (policy.onnx) with its contract (policy.json), for the torch-free runtime."""
    from efficienttrack.export import checkpoint_source, export_policy
    from efficienttrack.onnx_runtime import CONTRACT_FILE, ONNX_FILE
    from efficienttrack.policy import load_policy

    check_output_folder(out)
    pi_phi = load_policy(policy, "cpu")
    _lock(ctx, out)
    prepare_output_folder(out, (ONNX_FILE, CONTRACT_FILE), force)
    export_policy(pi_phi, out, checkpoint_source(policy))
    typer.echo(f"exported {policy} to {out / ONNX_FILE} with its contract {out / CONTRACT_FILE}")


@app.command("round")
def round_command(
    ctx: typer.Context,
    model: Annotated[Path, typer.Option("--model", help="The previous round's model checkpoint (model.pt).")],
    policy: Annotated[Path, typer.Option("--policy", help="The previous round's policy checkpoint, the one deployed.")],
    data: Annotated[
        list[Path], typer.Option("--data", help="Episodes recorded with --policy deployed: the new data (repeatable).")
    ],
    out: Annotated[
        Path,
        typer.Option("--out", help="Folder for the round: model.pt, policy.pt (+ .json), their logs, round.json."),
    ],
    old_data: Annotated[
        list[Path] | None, typer.Option("--old-data", help="Earlier episodes to train on as well (repeatable).")
    ] = None,
    held_out: HeldOutOpt = None,
    preset_name: Annotated[
        str, typer.Option("--preset", help="Training schedule preset: paper, cpu or tiny (sizes: the checkpoints').")
    ] = "cpu",
    steps_model: Annotated[int | None, typer.Option("--steps-model", help="Override the model's optimizer steps.")] = None,
    steps_policy: Annotated[int | None, typer.Option("--steps-policy", help="Override the policy's optimizer steps.")] = None,
    warm_budget: Annotated[
        float,
        typer.Option("--warm-budget", help="Share of the preset's optimizer steps a warm round trains (as run --rounds)."),
    ] = RunConfig.warm_budget,
    device: DeviceOpt = "auto",
    seed: TrainSeedOpt = 0,
    threads: ThreadsOpt = 1,
    recursive: RecursiveOpt = False,
    force: Annotated[
        bool,
        typer.Option(
            "--force",
            help="Start afresh: delete an earlier round's outputs in OUT (other files are kept) instead of refusing it.",
        ),
    ] = False,
) -> None:
    """One round of continual learning: model and policy of round k from round k−1's and the newly recorded episodes.

    Both start from the given checkpoints (warm start). Prints and writes OUT/round.json: the model's 20-step error
    on the new episodes (and on --held-out) before and after, and the tracking error recorded and model-predicted.
    An interrupted round resumes (rerun the same command); a finished one is refused without --force.
    """
    from efficienttrack.dynamics import MODEL_PRESETS, load_model
    from efficienttrack.next_round import ROUND_JSON, ROUND_OUTPUTS, next_round
    from efficienttrack.policy import POLICY_PRESETS, load_policy

    check_output_folder(out)
    _set_threads(threads)
    if not warm_budget > 0:
        raise EfficientTrackError(f"--warm-budget {warm_budget}: must be a share > 0 of the preset's steps")
    model_schedule = _learn_preset(MODEL_PRESETS, preset_name, steps_model, warm_budget)
    policy_schedule = _learn_preset(POLICY_PRESETS, preset_name, steps_policy, warm_budget)
    g_theta, _ = _warm_start("--model", model, load_model, model_schedule, device)
    pi_phi, _ = _warm_start("--policy", policy, load_policy, policy_schedule, device)
    new, old = load_records(data, recursive), load_records(old_data, recursive) if old_data else []
    held = load_records(held_out, recursive) if held_out else []
    _lock(ctx, out)
    interrupted = out.is_dir() and not (out / ROUND_JSON).exists() and all(e.name in ROUND_OUTPUTS for e in out.iterdir())
    if force or not interrupted:
        prepare_output_folder(out, ROUND_OUTPUTS, force)
    inputs = {
        "model": str(model.resolve()),
        "policy": str(policy.resolve()),
        "data": [str(p.resolve()) for p in data],
        "old_data": [str(p.resolve()) for p in old_data or []],
        "held_out": [str(p.resolve()) for p in held_out or []],
        "preset": preset_name,
        "seed": seed,
    }
    report = next_round(
        g_theta, pi_phi, new, old, model_schedule, policy_schedule, device, seed, out, held, inputs=inputs
    ).report
    typer.echo(
        f"round on {report.new_episodes} new + {report.old_episodes} old episodes ({report.model_steps} model, "
        f"{report.policy_steps} policy steps, {report.seconds:.0f} s)\n"
        f"model 20-step MPE on the new episodes: {report.model_mpe_before_deg:.3f}° → {report.model_mpe_after_deg:.3f}°"
    )
    if report.held_out_mpe_before_deg is not None:
        typer.echo(f"model 20-step MPE held out: {report.held_out_mpe_before_deg:.3f}° → {report.held_out_mpe_after_deg:.3f}°")
    typer.echo(
        f"tracking MAE recorded with --policy: {report.recorded_mae_deg:.3f}°; predicted by the new model: a = 0 "
        f"{report.predicted_pd_deg:.3f}°, --policy {report.predicted_before_deg:.3f}°, new policy "
        f"{report.predicted_after_deg:.3f}°\nwrote {out / 'model.pt'}, {out / 'policy.pt'}, {out / ROUND_JSON}"
    )


SIM_VS_REAL_PREFIX = "sim_vs_real_"
"""Name prefix of the plots ``sim fidelity --plot`` draws."""
LogsOpt = Annotated[list[Path], typer.Option("--logs", help="Episode files or folders (logs with the PWM u; repeatable).")]


FIT = FitConfig()
"""The fit's default settings, shown as the ``sim calibrate`` options' defaults."""


LOOP = LoopConfig()
"""Where the ``deploy`` options take their defaults from."""


@app.command("deploy")
def deploy_command(
    ctx: typer.Context,
    refs: Annotated[Path, typer.Option("--refs", help="Folder of reference trajectories (.npy/.csv, rad), run in turn.")],
    out: Annotated[
        Path, typer.Option("--out", help="Output folder: <reference>.jsonl per run (a line per tick), deploy.json.")
    ],
    policy: Annotated[
        Path | None,
        typer.Option(
            "--policy",
            help="Policy checkpoint (policy.pt), or an export folder (policy.onnx + policy.json, run in ONNX Runtime on the "
            "CPU); without, the raw reference (a = 0).",
        ),
    ] = None,
    arm: Annotated[bool, typer.Option("--arm", help="Allow the machine to move (nothing is sent without it).")] = False,
    shadow: Annotated[
        bool, typer.Option("--shadow", help="Compute and log the adjustment, send the raw reference (run this first).")
    ] = False,
    system: SystemOpt = None,
    plant: PlantOpt = None,
    pd: PdOpt = "xe75",
    system_opt: SystemOpts = None,
    limits: LimitsOpt = None,
    machine: Annotated[
        str | None, typer.Option("--machine", help="A real machine's adapter, module.path:callable (needs --limits).")
    ] = None,
    machine_opt: Annotated[
        list[str] | None, typer.Option("--machine-opt", help="key=value option of the adapter (repeatable).")
    ] = None,
    fast: Annotated[
        bool, typer.Option("--fast", help="Simulator only: a simulated clock, as fast as it computes (no real-time timing).")
    ] = False,
    hold_after: Annotated[int, typer.Option("--hold-after", help="Overruns in a row from which a = 0.")] = LOOP.hold_after,
    stop_after: Annotated[int, typer.Option("--stop-after", help="Overruns in a row that stop the run.")] = LOOP.stop_after,
    stale_ticks: Annotated[
        float, typer.Option("--stale-ticks", help="A reading older than this many periods: a = 0.")
    ] = LOOP.stale_ticks,
    stop_stale_ticks: Annotated[
        float, typer.Option("--stop-stale-ticks", help="The last good reading older than this many periods: stop.")
    ] = LOOP.stop_stale_ticks,
    device: Annotated[str, typer.Option("--device", help="cpu, cuda or auto.")] = "cpu",
    force: Annotated[bool, typer.Option("--force", help="Write into a non-empty OUT: first delete its logs.")] = False,
) -> None:
    """The policy at 20 Hz on absolute deadlines against the simulator or a machine, with watchdogs; a log per tick.

    Nothing is sent without --arm, because even shadow mode moves the machine (along the raw reference). Start with
    --arm --shadow; every run starts and ends with a = 0. Exit code 1 when a watchdog stopped a run.
    """
    from efficienttrack.deploy import DEPLOY_OUTPUTS, deploy, deployment_parts
    from efficienttrack.references import load_references

    if not arm:
        raise EfficientTrackError(
            "deploy sends references to the machine: add --arm to allow motion "
            "(with --shadow the adjustment is only logged and the raw reference is sent; start there)"
        )
    check_output_folder(out)
    cfg = LoopConfig(hold_after=hold_after, stop_after=stop_after, stale_ticks=stale_ticks, stop_stale_ticks=stop_stale_ticks)
    references = load_references(refs)
    spec = _system_spec(system, plant, pd, system_opt, limits)
    runtime, make_machine, machine_limits, clock = deployment_parts(
        spec, machine, parse_options(machine_opt, "--machine-opt"), policy, device, fast
    )
    _lock(ctx, out)
    prepare_output_folder(out, DEPLOY_OUTPUTS, force)
    settings = {"policy": None if policy is None else str(policy), "machine": machine, "system": spec.to_dict(), "fast": fast}

    def report(result) -> None:
        s = result.summary()
        late = s.get("lateness_ms", {})
        typer.echo(
            f"{result.name}: {result.reason}, {result.ticks} ticks, lateness p99 {late.get('p99', 0):.2f} ms "
            f"max {late.get('max', 0):.2f} ms, overruns {s.get('overrun', 0)}, stale {s.get('stale', 0)}, "
            f"fallbacks {s.get('fallback', 0)}" + (f" ({result.error})" if result.error else "")
        )

    results = deploy(references, runtime, make_machine, machine_limits, out, cfg, clock, shadow, settings, report)
    if results[-1].stopped:
        typer.secho(f"stopped: {results[-1].name}: {results[-1].reason}; logs in {out}", fg=typer.colors.RED, err=True)
        raise typer.Exit(1)
    typer.echo(f"{len(results)} run(s) done ({'shadow' if shadow else 'armed'}); logs in {out}")


def parse_ints(text: str, flag: str) -> tuple[int, ...]:
    """Parse a comma-separated list of integers given to an option, e.g. ``--delays 2,3,4``.

    Args:
        text: the option's value as given on the command line.
        flag: the option's name, used in error messages.

    Returns:
        The integers, in the order given.

    Raises:
        EfficientTrackError: an item is not an integer.
    """
    try:
        return tuple(int(item) for item in text.split(","))
    except ValueError as exc:
        raise EfficientTrackError(f"{flag} '{text}': expected comma-separated integers, e.g. 2,3,4") from exc


@sim_app.command("calibrate")
def sim_calibrate_command(
    logs: LogsOpt,
    out: Annotated[Path, typer.Option("--out", help="JSON preset to write (load it with --system-opt params_file=...).")],
    start: Annotated[Path | None, typer.Option("--start", help="Preset to start from (default: the shipped xe75).")] = None,
    delays: Annotated[
        str, typer.Option("--delays", help="Candidate transport delays, steps, comma-separated (e.g. 2,3,4).")
    ] = ",".join(map(str, FIT.delays)),
    max_windows: Annotated[int, typer.Option("--max-windows", help="Fit windows of each kind at most.")] = FIT.max_windows,
    max_nfev: Annotated[int, typer.Option("--max-nfev", help="Residual evaluations per least-squares stage.")] = FIT.max_nfev,
    max_ref_jitter: Annotated[
        float, typer.Option("--max-ref-jitter", help="Leave out episodes whose q_ref − q_des jitters more, rad.")
    ] = FIT.max_ref_jitter,
    recursive: RecursiveOpt = False,
) -> None:
    """Fit the hydraulic simulator to a machine's PD logs (PWM → motion) and write the preset."""
    from efficienttrack.systems.fit import calibrate, load_logs, save_params
    from efficienttrack.systems.hydraulic import HydraulicParams

    check_output_file(out)
    candidates = parse_ints(delays, "--delays")
    config = replace(FIT, delays=candidates, max_windows=max_windows, max_nfev=max_nfev, max_ref_jitter=max_ref_jitter)
    first = HydraulicParams.load(start) if start is not None else None
    result = calibrate(load_logs(logs, recursive=recursive), first, config, progress=typer.echo)
    save_params(result.params, out)
    typer.echo(
        f"open-loop window error (deg) {[round(float(v), 3) for v in result.open_loop_deg]}, closed-loop "
        f"{[round(float(v), 3) for v in result.closed_loop_deg]}; wrote {out}"
    )


@sim_app.command("fidelity")
def sim_fidelity_command(
    logs: LogsOpt,
    system: SystemOpt = None,
    plant: PlantOpt = None,
    pd: PdOpt = "xe75",
    system_opt: SystemOpts = None,
    json_output: Annotated[bool, typer.Option("--json", help="Print one JSON line.")] = False,
    plot: Annotated[Path | None, typer.Option("--plot", help="Folder for sim-vs-real trace plots.")] = None,
    force: Annotated[
        bool, typer.Option("--force", help="Plot into a non-empty --plot folder: first delete its sim_vs_real_*.png.")
    ] = False,
    episodes: Annotated[int, typer.Option("--episodes", help="Episodes to plot.")] = 3,
    stride: Annotated[int, typer.Option("--stride", help="Steps between open-loop window starts.")] = 10,
    min_ref_jitter: Annotated[
        float, typer.Option("--min-ref-jitter", help="Leave out episodes whose q_ref − q_des jitters less, rad.")
    ] = 0.0,
    max_ref_jitter: Annotated[
        float | None, typer.Option("--max-ref-jitter", help="Leave out episodes whose q_ref − q_des jitters more, rad.")
    ] = None,
    recursive: RecursiveOpt = False,
) -> None:
    """Compare a simulator with real PD logs: closed-loop tracking MAE ratio, open-loop 20-step error and travel."""
    from efficienttrack.plots import plot_sim_vs_real
    from efficienttrack.systems.fit import fidelity, load_logs, select_by_jitter

    if plot is not None:
        check_output_folder(plot, "--plot")
    spec = _system_spec(system, plant, pd, system_opt)
    system_view, plant_view = spec.open(), spec.open_plant()
    records = load_logs(logs, need_u=plant_view is not None, recursive=recursive)
    if episodes < 0:
        raise EfficientTrackError(f"--episodes {episodes}: expected ≥ 0 episodes to plot")
    if min_ref_jitter != 0 or max_ref_jitter is not None:
        high = math.inf if max_ref_jitter is None else max_ref_jitter
        records = select_by_jitter(records, min_ref_jitter, high, option="--min-ref-jitter/--max-ref-jitter")
    if plot is not None:
        prepare_output_folder(plot, (f"{SIM_VS_REAL_PREFIX}*.png",), force, option="--plot")
    result = fidelity(records, system_view, plant_view, stride=stride)
    if plot is not None:
        for i in range(min(episodes, len(records))):
            n = len(records[i])
            name = records[i].meta.get("name", f"episode{i}")
            path = plot / f"{SIM_VS_REAL_PREFIX}{name}.png"
            plot_sim_vs_real(records[i].q, result.q_sim[:n, i], records[i].q_des, path, name)
    report = result.to_json()
    if json_output:
        typer.echo(json.dumps(finite_json(report, "sim fidelity"), allow_nan=False))
        return

    def fmt(values: list[float | None] | None, unit: str = "°") -> str:
        if values is None:
            return "n/a (no plant)"
        return ", ".join("n/a" if v is None else f"{v:.3f}{unit}" for v in values)

    typer.echo(f"{len(records)} episodes; joints boom, arm, bucket, swing")
    typer.echo(f"closed-loop PD MAE real:   {fmt(report['closed_loop']['real_mae_deg'])}")
    typer.echo(f"closed-loop PD MAE sim:    {fmt(report['closed_loop']['sim_mae_deg'])}")
    typer.echo(f"ratio sim/real:            {fmt(report['closed_loop']['ratio'], '')}")
    typer.echo(f"open-loop 20-step error:   {fmt(report['open_loop']['mpe20_deg'])}")
    typer.echo(f"open-loop travel real/sim: {fmt(report['open_loop']['travel_ratio20'], '')}")


def _one_line_warning(
    message: Warning | str, category: type[Warning], filename: str, lineno: int, line: str | None = None
) -> str:
    return f"warning: {message}\n"


def main() -> None:
    """Entry point: run the app; user-facing errors and a disk or folder refusing a file give one line and exit code 2."""
    warnings.formatwarning = _one_line_warning
    try:
        app()
    except (EfficientTrackError, OSError) as exc:
        if isinstance(exc, OSError) and exc.errno is None:  # not the system refusing a file: a bug, keep its traceback
            raise
        typer.secho(f"error: {os_error_text(exc) if isinstance(exc, OSError) else exc}", fg=typer.colors.RED, err=True)
        sys.exit(2)

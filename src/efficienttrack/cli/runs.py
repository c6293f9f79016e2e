"""Commands that run the whole method or its evaluation in a resumable run folder: ``evaluate``, ``run``, ``demo``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from efficienttrack.cli.common import (
    ConfigOpt,
    DeviceOpt,
    LimitsOpt,
    PdOpt,
    PlantOpt,
    PresetOpt,
    RunDeviceOpt,
    RunSeedOpt,
    SetOpt,
    SystemOpt,
    SystemOpts,
    ThreadsOpt,
    _lock,
    _set_threads,
    _settings,
    _system_spec,
    app,
    wide_console,
)
from efficienttrack.core.fileio import check_output_folder, prepare_output_folder

RunForceOpt = Annotated[
    bool,
    typer.Option(
        "--force",
        help="Start afresh: delete the earlier run's outputs in OUT (records, checkpoints and training states, model, "
        "policy, metrics, plots; other files are kept) instead of resuming it or refusing other settings.",
    ),
]

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

TimeBudgetOpt = Annotated[
    float | None,
    typer.Option(
        "--time-budget",
        help="Minutes for the whole run, all rounds: every training's steps are scaled down to fit, from step times "
        "measured on this machine, or, when the minutes leave room, the model's up to 3 ×, then the policy's up to 1.5 × "
        "(a target, not a guarantee; default: the configured steps).",
    ),
]

PlotsOpt = Annotated[
    int | None, typer.Option("--plots", help="Draw tracking plots of the first N test references (default: every one).")
]


def _prepare_run_folder(out: Path, outputs: tuple[str, ...], force: bool) -> None:
    """With ``force`` delete the run's ``outputs`` in OUT; else refuse an OUT holding other files and no run to resume."""
    resumable = (out / "run.json").exists() or not out.is_dir() or all(entry.name in outputs for entry in out.iterdir())
    if force or not resumable:
        prepare_output_folder(out, outputs, force)


@app.command("evaluate")
def evaluate_command(
    ctx: typer.Context,
    refs: Annotated[Path, typer.Option("--refs", help="Folder of reference trajectories (.npy/.csv, rad).")],
    out: Annotated[Path, typer.Option("--out", help="Output folder: records/, metrics.json, plots/, run.log.")],
    system: SystemOpt = None,
    plant: PlantOpt = None,
    pd: PdOpt = None,
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
    from efficienttrack.data.references import load_references
    from efficienttrack.workflow.evaluation import EVALUATE_JSON, EVALUATE_OUTPUTS, evaluate

    check_output_folder(out)
    spec, references = _system_spec(system, plant, pd, system_opt, limits), load_references(refs)
    _lock(ctx, out)
    interrupted = (out / EVALUATE_JSON).exists() and not (out / "metrics.json").exists()
    if force or not interrupted:
        prepare_output_folder(out, EVALUATE_OUTPUTS, force)
    evaluate(spec, references, out, policy, device, wide_console(), plots)


@app.command("run")
def run_command(
    ctx: typer.Context,
    train_refs: Annotated[Path, typer.Option("--train-refs", help="Folder of training references.")],
    test_refs: Annotated[Path, typer.Option("--test-refs", help="Folder of held-out test references.")],
    out: Annotated[Path, typer.Option("--out", help="Output folder; rerunning resumes where it stopped.")],
    system: SystemOpt = None,
    plant: PlantOpt = None,
    pd: PdOpt = None,
    system_opt: SystemOpts = None,
    limits: LimitsOpt = None,
    preset_name: PresetOpt = "cpu",
    config: ConfigOpt = None,
    overrides: SetOpt = None,
    seed: RunSeedOpt = None,
    device: RunDeviceOpt = None,
    rounds: RoundsOpt = None,
    round_data: RoundDataOpt = None,
    time_budget: TimeBudgetOpt = None,
    threads: ThreadsOpt = 1,
    plots: PlotsOpt = None,
    force: RunForceOpt = False,
) -> None:
    """The whole method: collect, train model and policy, evaluate PD alone vs EfficientTrack on the test references."""
    from efficienttrack.data.references import load_references
    from efficienttrack.workflow.pipeline import RUN_OUTPUTS, run_pipeline

    check_output_folder(out)
    _set_threads(threads)
    spec = _system_spec(system, plant, pd, system_opt, limits)
    cfg = _settings(
        preset_name, config, overrides, seed=seed, device=device, rounds=rounds, round_data=round_data, time_budget=time_budget
    )
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
    overrides: SetOpt = None,
    seed: RunSeedOpt = None,
    device: RunDeviceOpt = None,
    rounds: RoundsOpt = None,
    round_data: RoundDataOpt = None,
    time_budget: TimeBudgetOpt = None,
    threads: ThreadsOpt = 1,
    plots: PlotsOpt = None,
    force: RunForceOpt = False,
) -> None:
    """The whole method on the built-in xe75 simulator with generated references (32 train / 8 test)."""
    from efficienttrack.workflow.pipeline import DEMO_OUTPUTS, demo

    check_output_folder(out)
    _set_threads(threads)
    cfg = _settings(
        preset_name, config, overrides, seed=seed, device=device, rounds=rounds, round_data=round_data, time_budget=time_budget
    )
    _lock(ctx, out)
    _prepare_run_folder(out, DEMO_OUTPUTS, force)
    demo(out, cfg, console=wide_console(), max_plots=plots)

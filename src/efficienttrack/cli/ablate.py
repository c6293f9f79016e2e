"""The ``ablate`` command: EfficientTrack once per variant of one setting × seed, at equal data, locally or on Ray."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from efficienttrack.cli.common import LimitsOpt, PdOpt, PlantOpt, SystemOpt, SystemOpts, _lock, _system_spec, app
from efficienttrack.cli.sim import parse_ints
from efficienttrack.cli.study import (
    AddressOpt,
    ExecutorOpt,
    JobsOpt,
    JobThreadsOpt,
    StudyPresetOpt,
    StudySetOpt,
    TestRefsOpt,
    TrainRefsOpt,
    _study_settings,
    comma_names,
)
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import check_output_folder, prepare_output_folder


@app.command("ablate")
def ablate_command(
    ctx: typer.Context,
    ablation_name: Annotated[str, typer.Argument(metavar="ABLATION", help="noise-ratio, k-smooth or history.")],
    out: Annotated[Path, typer.Option("--out", help="Ablation folder; rerunning skips the finished jobs.")],
    train_refs: TrainRefsOpt = None,
    test_refs: TestRefsOpt = None,
    system: SystemOpt = None,
    plant: PlantOpt = None,
    pd: PdOpt = None,
    system_opt: SystemOpts = None,
    limits: LimitsOpt = None,
    values: Annotated[
        str | None,
        typer.Option(
            "--values",
            help="Comma-separated values of the setting (default: noise-ratio 0:1,1:0,9:1,9:2,9:3,9:4; "
            "k-smooth 0,0.5,1,2; history 1,2,5,10,20).",
        ),
    ] = None,
    seeds: Annotated[str, typer.Option("--seeds", help="Comma-separated seeds, one job per variant and seed.")] = "0",
    passes: Annotated[
        int | None, typer.Option("--passes", help="Collection passes of every variant (default: the preset's, full 10).")
    ] = None,
    preset_name: StudyPresetOpt = "cpu",
    overrides: StudySetOpt = None,
    executor: ExecutorOpt = "local",
    jobs: JobsOpt = 1,
    address: AddressOpt = None,
    threads: JobThreadsOpt = 1,
    report_only: Annotated[
        bool, typer.Option("--report-only", help="Run nothing: rebuild the table, ablation.json and figure from OUT's jobs.")
    ] = False,
    force: Annotated[
        bool,
        typer.Option(
            "--force", help="Start afresh: delete OUT's earlier ablation (its jobs and report; other files are kept)."
        ),
    ] = False,
) -> None:
    """Ablate one setting of EfficientTrack: the whole pipeline per variant and seed, every variant with the same passes.

    noise-ratio: the noisy:clean mix of the collection (the paper's Table II); k-smooth: the weight of the policy's
    smoothness term (Table III); history: the dynamics model's history length. Table (Markdown, CSV), ablation.json
    and figure in OUT, mean ± std over seeds. Each job writes OUT/jobs/efficienttrack-<variant>-s<seed>/; a rerun
    skips the finished ones. Exit code 1 when a job failed (the others still ran).
    """
    from efficienttrack.data.references import load_references
    from efficienttrack.study import ablation_jobs, ablation_report, get_ablation, make_ablation_study, run_ablation
    from efficienttrack.study.jobs import STUDY_CONFIG
    from efficienttrack.study.run import ABLATION_OUTPUTS

    ablation = get_ablation(ablation_name)
    if report_only:
        report = ablation_report(out)
        if report.ablation != ablation.name:
            raise EfficientTrackError(f"--out {out}: holds the ablation {report.ablation}, not {ablation.name}")
        typer.echo(report.markdown)
        return
    if train_refs is None or test_refs is None:
        raise EfficientTrackError(f"{'--train-refs' if train_refs is None else '--test-refs'}: needed to run an ablation")
    check_output_folder(out)
    spec = _system_spec(system, plant, pd, system_opt, limits)
    spec.open()  # a bad system spec or limits file is refused here, not by every job
    train, test, settings = load_references(train_refs), load_references(test_refs), _study_settings(preset_name, overrides)
    study = make_ablation_study(spec, train, test, preset_name, passes, settings)
    job_list = ablation_jobs(
        ablation, study, parse_ints(seeds, "--seeds"), None if values is None else comma_names(values, "--values")
    )
    _lock(ctx, out)
    resumable = (out / STUDY_CONFIG).exists() or all(entry.name in ABLATION_OUTPUTS for entry in out.iterdir())
    if force or not resumable:
        prepare_output_folder(out, ABLATION_OUTPUTS, force)
    result = run_ablation(ablation, study, job_list, out, executor, jobs, threads, address, log=typer.echo)
    typer.echo(result.report.markdown)
    typer.echo(f"table, ablation.json and figure in {out}")
    if result.failed:
        typer.secho(f"{len(result.failed)} job(s) failed: {', '.join(result.failed)}", fg=typer.colors.RED, err=True)
        raise typer.Exit(1)

"""The ``study`` command: methods × loops × seeds on one system and one train/test split, locally or on Ray."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from efficienttrack.cli.common import LimitsOpt, PdOpt, PlantOpt, SystemOpt, SystemOpts, _lock, _system_spec, app
from efficienttrack.cli.sim import parse_ints
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import check_output_folder, prepare_output_folder


def comma_names(text: str, flag: str) -> list[str]:
    """``a,b`` → ``["a", "b"]``; an empty item is an error naming ``flag``.

    Args:
        text: the option's value.
        flag: the option, for the error.

    Returns:
        The names, stripped.
    """
    names = [item.strip() for item in text.split(",")]
    if not all(names):
        raise EfficientTrackError(f"{flag} '{text}': expected comma-separated names, e.g. pd,efficienttrack")
    return names


def _study_settings(preset_name: str, overrides: list[str] | None):
    """EfficientTrack's settings in a study: its preset's run settings with the ``--set`` overrides (None without any).

    Each job's seed replaces ``seed`` (``--seeds``); an ablation's variant changes its one setting on top.
    """
    from efficienttrack.core.settings import canonical_preset
    from efficienttrack.study.jobs import STUDY_PRESETS
    from efficienttrack.workflow.config import apply_overrides, preset

    if not overrides:
        return None
    preset_name = canonical_preset(preset_name)
    if preset_name not in STUDY_PRESETS:
        raise EfficientTrackError(f"--preset '{preset_name}': unknown, choose one of {', '.join(STUDY_PRESETS)}")
    return apply_overrides(preset(STUDY_PRESETS[preset_name].run), overrides)


def _method_budgets(items: list[str]) -> dict[str, int]:
    """``["sac=50000", ...]`` → ``{"sac": 50000}``; a malformed item is an error naming ``--method-budget``."""
    budgets = {}
    for item in items:
        method, _, steps = item.partition("=")
        if not method.strip() or not steps.strip().isdigit():
            raise EfficientTrackError(f"--method-budget '{item}': expected METHOD=STEPS, e.g. sac=50000")
        budgets[method.strip()] = int(steps)
    return budgets


def _interaction_counts(text: str) -> list[int]:
    """``17672,35344`` → ``[17672, 35344]``; an item that is not a positive integer is an error naming ``--at``."""
    counts = []
    for item in text.split(","):
        if not item.strip().isdecimal() or int(item) == 0:
            raise EfficientTrackError(f"--at '{item.strip()}': expected positive interaction step counts, e.g. 17672,35344")
        counts.append(int(item))
    return counts


StudyPresetOpt = Annotated[
    str,
    typer.Option("--preset", help="tiny (tiny networks, minutes) or cpu (the cpu run preset, the baselines' cpu settings)."),
]
StudySetOpt = Annotated[
    list[str] | None,
    typer.Option(
        "--set",
        help="Change one of EfficientTrack's settings: section.field=value, e.g. model.history=5 (repeatable; "
        "`efficienttrack config show` lists them; the seed is each job's).",
    ),
]
ExecutorOpt = Annotated[str, typer.Option("--executor", help="local (this machine) or ray.")]
JobsOpt = Annotated[int, typer.Option("--jobs", help="Jobs at once (local processes, or CPUs of a local Ray instance).")]
AddressOpt = Annotated[
    str | None, typer.Option("--address", help="HOST:PORT of a running Ray cluster's head (default: a local instance).")
]
JobThreadsOpt = Annotated[int, typer.Option("--threads", help="torch CPU threads of each job (0: torch's default).")]
TrainRefsOpt = Annotated[Path | None, typer.Option("--train-refs", help="Folder of training references.")]
TestRefsOpt = Annotated[Path | None, typer.Option("--test-refs", help="Folder of held-out test references.")]
"""The options ``study`` and ``ablate`` share."""


@app.command("study")
def study_command(
    ctx: typer.Context,
    out: Annotated[Path, typer.Option("--out", help="Study folder; rerunning skips the finished jobs.")],
    train_refs: TrainRefsOpt = None,
    test_refs: TestRefsOpt = None,
    system: SystemOpt = None,
    plant: PlantOpt = None,
    pd: PdOpt = None,
    system_opt: SystemOpts = None,
    limits: LimitsOpt = None,
    methods: Annotated[
        str | None,
        typer.Option("--methods", help="Comma-separated: pd, efficienttrack, sac, ppo, tdmpc, supertrack, ilc (default all)."),
    ] = None,
    loops: Annotated[
        str, typer.Option("--loops", help="closed and/or open (open: only methods that have it; needs a plant).")
    ] = "closed",
    seeds: Annotated[str, typer.Option("--seeds", help="Comma-separated seeds, one job per method, loop and seed.")] = "0",
    budget: Annotated[
        int | None, typer.Option("--budget", help="Interaction steps per job (default: tiny 20,000, cpu 200,000).")
    ] = None,
    method_budget: Annotated[
        list[str] | None,
        typer.Option("--method-budget", help="METHOD=N: that method's interaction steps instead of --budget (repeatable)."),
    ] = None,
    validation: Annotated[
        int | None,
        typer.Option(
            "--validation",
            help="Training references held out of every method's training, on which the report selects each curve's "
            "point (default: a tenth of them, rounded down, e.g. 4 of 40; 0: none, no selection).",
        ),
    ] = None,
    preset_name: StudyPresetOpt = "cpu",
    overrides: StudySetOpt = None,
    method_set: Annotated[
        list[str] | None,
        typer.Option(
            "--method-set",
            help="Change one of a method's settings: METHOD.field=value, e.g. supertrack.policy.lr=1e-5 or "
            "sac.learning_rate=3e-5 (repeatable; baselines, and efficienttrack in the open loop; its closed loop: --set). "
            "The table names the changes.",
        ),
    ] = None,
    executor: ExecutorOpt = "local",
    jobs: JobsOpt = 1,
    address: AddressOpt = None,
    threads: JobThreadsOpt = 1,
    report_only: Annotated[
        bool, typer.Option("--report-only", help="Run nothing: rebuild the table, study.json and figure from OUT's jobs.")
    ] = False,
    force: Annotated[
        bool,
        typer.Option("--force", help="Start afresh: delete OUT's earlier study (its jobs and report; other files are kept)."),
    ] = False,
) -> None:
    """Compare methods on one system: each job trains one method with one seed; table, study.json and figure in OUT.

    Jobs run one after the other here by default, in a process pool with --jobs N, or on Ray with --executor ray.
    Each job writes its own folder OUT/jobs/<method>-<loop>-s<seed>/; a rerun skips the finished ones, and the
    report is rebuilt from the folders. Exit code 1 when a job failed (the others still ran).
    """
    from efficienttrack.data.references import load_references
    from efficienttrack.study import make_jobs, make_study, report, run_study
    from efficienttrack.study.jobs import STUDY_CONFIG
    from efficienttrack.study.run import STUDY_OUTPUTS

    if report_only:
        typer.echo(report(out).markdown)
        return
    if train_refs is None or test_refs is None:
        raise EfficientTrackError(f"{'--train-refs' if train_refs is None else '--test-refs'}: needed to run a study")
    check_output_folder(out)
    spec = _system_spec(system, plant, pd, system_opt, limits)
    spec.open()  # a bad system spec or limits file is refused here, not by every job
    budgets = _method_budgets(method_budget or [])
    settings = _study_settings(preset_name, overrides)
    study = make_study(
        spec, load_references(train_refs), load_references(test_refs), budget, preset_name, settings, budgets, validation,
        method_set or (),
    )  # fmt: skip
    names = None if methods is None else comma_names(methods, "--methods")
    job_list = make_jobs(study, names, comma_names(loops, "--loops"), parse_ints(seeds, "--seeds"))
    _lock(ctx, out)
    resumable = (out / STUDY_CONFIG).exists() or all(entry.name in STUDY_OUTPUTS for entry in out.iterdir())
    if force or not resumable:
        prepare_output_folder(out, STUDY_OUTPUTS, force)
    result = run_study(study, job_list, out, executor, jobs, threads, address, log=typer.echo)
    typer.echo(result.report.markdown)
    typer.echo(f"table, study.json and figure in {out}")
    if result.failed:
        typer.secho(f"{len(result.failed)} job(s) failed: {', '.join(result.failed)}", fg=typer.colors.RED, err=True)
        raise typer.Exit(1)


@app.command("study-plot")
def study_plot_command(
    folders: Annotated[
        list[Path],
        typer.Argument(help="Study folders (each a study's --out) of one system, or their results.json files."),
    ],
    out: Annotated[Path, typer.Option("--out", help="The figure to write (PNG).")],
    at: Annotated[
        str | None,
        typer.Option(
            "--at",
            help="Comma-separated interaction step counts N: also a table of each method's test MAE with at most N "
            "interaction steps (each seed's last curve point at or below N), e.g. 17672,176720.",
        ),
    ] = None,
) -> None:
    """One table and one MAE-against-interaction-time figure of several study folders (a study run in several sittings).

    A folder's results.json (every study writes one) stands for the folder: committed, it redraws the table and the
    figure without the runs.

    With --at, a second table compares the methods at equal interaction: one column per count N.
    """
    from efficienttrack.core.fileio import check_output_file
    from efficienttrack.study.report import combine
    from efficienttrack.study.tables import equal_interaction_table

    counts = None if at is None else _interaction_counts(at)
    check_output_file(out)
    result = combine(folders, out)
    typer.echo(result.markdown)
    if counts is not None:
        typer.echo(equal_interaction_table(result.entries, counts))
    typer.echo(f"figure: {out}")

"""Run a study or an ablation: claim its folder, skip the finished jobs, run the others on an executor, rebuild the report.

Study folder layout::

    OUT/study_config.json          what the study is (system, references, budget, preset): a rerun must match
    OUT/jobs/<method>-<loop>-s<seed>/
        result.json                written last by the finished job: a rerun skips it
        error.json                 why it failed (a rerun runs it again)
        job.log                    what it printed
        ...                        the method's own files (EfficientTrack: passes_<p>/, one run folder per pass count;
                                   in rounds: run/, one run folder, and points/round_<k>.json)
    OUT/study.json, study.md, study.csv, study.png   the report (:func:`efficienttrack.study.report.report`)

An ablation's folder has the same layout, its jobs named ``<method>-<variant>-s<seed>``, its ``study_config.json``
naming the ablation, and its report ``ablation.json``, ``.md``, ``.csv``, ``.png``
(:func:`efficienttrack.study.ablation_report.ablation_report`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.provenance import claim_folder
from efficienttrack.study.ablation_report import OUTPUTS as ABLATION_REPORT
from efficienttrack.study.ablation_report import AblationReport, ablation_report
from efficienttrack.study.ablations import Ablation
from efficienttrack.study.executors import EXECUTORS, Outcome, run_local, run_ray
from efficienttrack.study.jobs import JOBS, RESULT, STUDY_CONFIG, Job, Study, job_folder
from efficienttrack.study.report import OUTPUTS, Report, read_result, report
from efficienttrack.study.summary import selected_point

STUDY_OUTPUTS = (STUDY_CONFIG, JOBS, *OUTPUTS)
"""What a study writes in its folder: a fresh start (``--force``) deletes these."""
ABLATION_OUTPUTS = (STUDY_CONFIG, JOBS, *ABLATION_REPORT)
"""What an ablation writes in its folder: a fresh start (``--force``) deletes these."""


@dataclass(frozen=True)
class StudyResult:
    """Outcome of :func:`run_study` or :func:`run_ablation`.

    Attributes:
        out: the study folder.
        ran: names of the jobs that ran and finished now.
        skipped: names of the jobs found finished and skipped.
        failed: job name → error, of the jobs that failed now.
        report: the rebuilt report (every finished job in the folder): the study's, or the ablation's.
    """

    out: Path
    ran: tuple[str, ...]
    skipped: tuple[str, ...]
    failed: dict[str, str]
    report: Report | AblationReport


def progress_line(outcome: Outcome, count: int, total: int) -> str:
    """One line saying how a job ended: its final point, and the point selected on validation references if it has one.

    E.g. ``[2/6] efficienttrack-closed-s0 done in 41 s: final MAE 0.52° at 176,720 interaction steps; selected on
    validation: 0.50° at 88,360``.

    Args:
        outcome: the job's outcome.
        count: how many jobs have ended, this one included.
        total: jobs to run.

    Returns:
        The line.
    """
    if outcome.result is None:
        return f"[{count}/{total}] {outcome.name} FAILED: {outcome.error}"
    final = max(outcome.result["curve"], key=lambda p: p["interaction_steps"])
    line = (
        f"[{count}/{total}] {outcome.name} done in {outcome.result['wall_seconds']:.0f} s: "
        f"final MAE {final['metrics']['mae_deg']:.2f}° at {final['interaction_steps']:,} interaction steps"
    )
    chosen = selected_point(outcome.result["curve"])
    if chosen is None:
        return line
    return f"{line}; selected on validation: {chosen['metrics']['mae_deg']:.2f}° at {chosen['interaction_steps']:,}"


def run_jobs(
    identity: dict[str, Any],
    jobs: Sequence[Job],
    out: str | Path,
    executor: str = "local",
    workers: int = 1,
    threads: int = 1,
    address: str | None = None,
    log: Callable[[str], None] = print,
    what: str = "study",
) -> tuple[Path, tuple[str, ...], tuple[str, ...], dict[str, str]]:
    """Claim ``out`` for the work ``identity`` describes, then run the jobs not finished yet, each in its own folder.

    Args:
        identity: what the work is, kept in ``OUT/study_config.json`` (a folder holding other work is refused).
        jobs: the jobs.
        out: the folder (see the module docstring).
        executor: ``local`` (this process, or a process pool with ``workers`` > 1) or ``ray``.
        workers: jobs at once: processes of the local pool, or CPUs of a local Ray instance (× ``threads``).
        threads: torch CPU threads of each job (0: torch's default).
        address: a Ray cluster's ``HOST:PORT`` (``ray`` only; None: a local instance).
        log: where the progress lines go.
        what: ``study`` or ``ablation``: the work's name in the progress lines and the refusal.

    Returns:
        The folder (absolute), the jobs that ran and finished now, those found finished and skipped, and job name →
        error of those that failed now.

    Raises:
        EfficientTrackError: an unknown executor, ``workers`` < 1, ``threads`` < 0, ``address`` without Ray, ``out``
            holding other work, or Ray unable to start or connect.
    """
    if executor not in EXECUTORS:
        raise EfficientTrackError(f"--executor {executor}: unknown, choose one of {', '.join(EXECUTORS)}")
    if not isinstance(workers, int) or workers < 1:
        raise EfficientTrackError(f"--jobs {workers}: expected a number of jobs at once ≥ 1")
    if not isinstance(threads, int) or threads < 0:
        raise EfficientTrackError(f"--threads {threads}: expected ≥ 0")
    if address is not None and executor != "ray":
        raise EfficientTrackError(f"--address {address}: only with --executor ray")
    out = Path(out).resolve()  # as the workers of a cluster see it, on a shared file system
    other = {
        "study": "a study of another system, references, budget, preset or settings, or an ablation",
        "ablation": "a study, or an ablation of another kind, system, references, passes or preset",
    }
    claim_folder(
        out / STUDY_CONFIG, identity, f"this folder holds {other[what]}; use another --out, or --force to start afresh"
    )
    (out / JOBS).mkdir(exist_ok=True)
    todo = [job for job in jobs if read_result(job_folder(out, job.name) / RESULT) is None]
    skipped = tuple(job.name for job in jobs if job not in todo)
    count = f"{len(jobs)} job" + ("" if len(jobs) == 1 else "s")
    log(f"{what} {out}: {count}, {len(skipped)} finished earlier (skipped), {len(todo)} to run ({executor})")
    ended: list[Outcome] = []

    def on_done(outcome: Outcome) -> None:
        ended.append(outcome)
        log(progress_line(outcome, len(ended), len(todo)))

    if todo:
        if executor == "local":
            run_local(todo, out, workers, threads, on_done)
        else:
            run_ray(todo, out, threads, address, workers * max(threads, 1), on_done)
    failed = {o.name: o.error or "" for o in ended if o.result is None}
    ran = tuple(o.name for o in ended if o.result is not None)
    return out, ran, skipped, failed


def run_study(
    study: Study,
    jobs: Sequence[Job],
    out: str | Path,
    executor: str = "local",
    workers: int = 1,
    threads: int = 1,
    address: str | None = None,
    log: Callable[[str], None] = print,
) -> StudyResult:
    """Run the jobs not finished yet, each in its own folder, then rebuild the report from every job folder.

    Args:
        study: the study (``OUT/study_config.json`` records it; a folder holding another study is refused).
        jobs: its jobs (:func:`~efficienttrack.study.methods.make_jobs`).
        out: the study folder (see the module docstring).
        executor: ``local`` (this process, or a process pool with ``workers`` > 1) or ``ray``.
        workers: jobs at once: processes of the local pool, or CPUs of a local Ray instance (× ``threads``).
        threads: torch CPU threads of each job (0: torch's default).
        address: a Ray cluster's ``HOST:PORT`` (``ray`` only; None: a local instance).
        log: where the progress lines go.

    Returns:
        What ran, what was skipped, what failed, and the report.

    Raises:
        EfficientTrackError: an unknown executor, ``workers`` < 1, ``threads`` < 0, ``address`` without Ray, a job of
            another study, ``out`` holding another study, or Ray unable to start or connect.
    """
    if any(job.study is not study for job in jobs):
        raise EfficientTrackError("run_study: every job must belong to the study given")
    out, ran, skipped, failed = run_jobs(study.identity(), jobs, out, executor, workers, threads, address, log)
    return StudyResult(out, ran, skipped, failed, report(out))


def run_ablation(
    ablation: Ablation,
    study: Study,
    jobs: Sequence[Job],
    out: str | Path,
    executor: str = "local",
    workers: int = 1,
    threads: int = 1,
    address: str | None = None,
    log: Callable[[str], None] = print,
) -> StudyResult:
    """Run an ablation's jobs not finished yet, each in its own folder, then rebuild its report from every job folder.

    ``OUT/study_config.json`` records the study and the ablation's name: a folder holding a study or another ablation
    is refused. Variants (values) and seeds may be added to a folder by a rerun.

    Args:
        ablation: the ablation (:data:`~efficienttrack.study.ablations.ABLATIONS`).
        study: its study (:func:`~efficienttrack.study.ablations.make_ablation_study`).
        jobs: its jobs (:func:`~efficienttrack.study.ablations.ablation_jobs`).
        out: the ablation folder (the study's layout; the report is ``ablation.{json,md,csv,png}``).
        executor: ``local`` or ``ray``.
        workers: jobs at once.
        threads: torch CPU threads of each job.
        address: a Ray cluster's ``HOST:PORT`` (``ray`` only).
        log: where the progress lines go.

    Returns:
        What ran, what was skipped, what failed, and the report.

    Raises:
        EfficientTrackError: as :func:`run_study`, or a job that is not a variant of this study.
    """
    if any(job.study is not study or job.variant is None for job in jobs):
        raise EfficientTrackError("run_ablation: every job must be a variant of the study given")
    identity = {**study.identity(), "ablation": ablation.name}
    out, ran, skipped, failed = run_jobs(identity, jobs, out, executor, workers, threads, address, log, "ablation")
    return StudyResult(out, ran, skipped, failed, ablation_report(out))

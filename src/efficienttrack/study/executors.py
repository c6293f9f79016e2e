"""Where a study's jobs run: in this process, a local process pool, or a Ray cluster (one task per job).

Every executor calls :func:`execute` once per job, which runs the method in the job's folder and writes
``result.json`` last (or ``error.json`` when the method fails): a job's failure is an :class:`Outcome` with its
error, never the end of the others. A local study stopped by Ctrl-C, SIGTERM or SIGHUP stops its worker processes
too (:func:`process_pool`): a job left running would go on writing its folder unseen, beside the rerun's.
"""

from __future__ import annotations

import logging
import multiprocessing
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager, redirect_stderr, redirect_stdout
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import write_json
from efficienttrack.core.provenance import provenance
from efficienttrack.core.stop_signals import stop_signals_as_interrupt
from efficienttrack.study.jobs import ERROR, RESULT, Job, job_folder
from efficienttrack.study.methods import METHODS

EXECUTORS = ("local", "ray")
"""``local``: this process (``workers`` = 1) or a process pool; ``ray``: a Ray cluster, or a local Ray instance."""
RAY_OBJECT_STORE_BYTES = 200 * 1024**2
"""Object store of a local Ray instance the study starts: jobs exchange only small results."""
JOB_LOG = "job.log"
"""What a job printed (progress of its trainings), in its folder."""


class Outcome(NamedTuple):
    """How a job ended.

    Attributes:
        name: the job's name.
        result: the content of its ``result.json``, or None when it failed.
        error: None, or what went wrong (one line).
    """

    name: str
    result: dict[str, Any] | None
    error: str | None


def check_curve(curve: object) -> list[dict[str, Any]]:
    """A method's curve, checked: a non-empty list of points with integer interaction steps and a finite MAE.

    Args:
        curve: what the method returned.

    Returns:
        The points, sorted by interaction steps.

    Raises:
        EfficientTrackError: anything else (saying what is wrong).
    """
    if not isinstance(curve, list) or not curve:
        raise EfficientTrackError(f"the method returned {type(curve).__name__} {curve!r:.80}, not a non-empty list of points")
    for i, p in enumerate(curve):
        steps = p.get("interaction_steps") if isinstance(p, dict) else None
        metrics = p.get("metrics") if isinstance(p, dict) else None
        if not isinstance(steps, int) or isinstance(steps, bool) or steps < 0:
            raise EfficientTrackError(f"point {i} of the curve: 'interaction_steps' must be an integer ≥ 0, got {steps!r}")
        mae = metrics.get("mae_deg") if isinstance(metrics, dict) else None
        if not isinstance(mae, (int, float)) or not np.isfinite(mae):
            raise EfficientTrackError(f"point {i} of the curve: 'metrics' must hold a finite 'mae_deg', got {mae!r}")
    return sorted(curve, key=lambda p: p["interaction_steps"])


def execute(job: Job, out: Path, threads: int = 1) -> Outcome:
    """Run one job in this process, in ``out/jobs/<name>/``; what every executor runs, once per job.

    What the method prints goes to the folder's ``job.log``. On success ``result.json`` is written last:
    ``{"job", "method", "loop", "seed", "budget", "curve": [point, ...] sorted by interaction steps, "wall_seconds",
    "provenance"}`` (and ``"variant"``: name, label, overrides, for an ablation's job; ``"settings_changes"``: the
    ``--method-set`` changes it trained with, if any); on failure ``error.json``
    (``{"job", "error", "traceback"}``). ``"wall_seconds"`` is this sitting's wall time, evaluations included: a job
    resumed after a kill counts from the resume, while the wall times of its curve points carry on across the resume
    (what the study's table reports). Its provenance names the commit the job started from (``git_commit``,
    ``git_dirty``), and ``git_commit_at_end`` when another was checked out by the time it ended. torch uses ``threads``
    CPU threads while the job runs.

    Args:
        job: the job.
        out: the study folder.
        threads: torch CPU threads (0: leave torch's setting).

    Returns:
        The outcome; never raises for a failing method.
    """
    folder = job_folder(out, job.name)
    folder.mkdir(parents=True, exist_ok=True)
    previous = torch.get_num_threads()
    if threads:
        torch.set_num_threads(threads)
    start, began = time.perf_counter(), provenance()
    try:
        with open(folder / JOB_LOG, "a") as log, redirect_stdout(log), redirect_stderr(log):
            curve = check_curve(METHODS[job.method].run(job, folder))
    except Exception as exc:
        error = str(exc) if isinstance(exc, EfficientTrackError) else f"{type(exc).__name__}: {exc}"
        write_json(folder / ERROR, {"job": job.name, "error": error, "traceback": traceback.format_exc()})
        return Outcome(job.name, None, error)
    finally:
        torch.set_num_threads(previous)
    wall = time.perf_counter() - start
    ended = provenance(wall_seconds=wall)
    code = {key: began[key] for key in ("git_commit", "git_dirty")}  # what the job started from, not what is there now
    if ended["git_commit"] != began["git_commit"]:  # a commit made while it ran: modules it imported later may be it
        code["git_commit_at_end"] = ended["git_commit"]
    result = {
        "job": job.name,
        "method": job.method,
        "loop": job.loop,
        "seed": job.seed,
        "budget": job.budget,
        "curve": curve,
        "wall_seconds": round(wall, 2),
        "provenance": {**ended, **code},
    }
    if job.variant is not None:
        result["variant"] = job.variant.to_dict()
    if job.settings_changes:
        result["settings_changes"] = list(job.settings_changes)
    (folder / ERROR).unlink(missing_ok=True)
    write_json(folder / RESULT, result)
    return Outcome(job.name, result, None)


@contextmanager
def process_pool(workers: int) -> Iterator[ProcessPoolExecutor]:
    """A pool of ``workers`` spawned processes (no state shared) whose workers end with the block, however it ends.

    Leaving the block normally, or by an error, waits for the submitted work, as ``with ProcessPoolExecutor()`` does.
    Ctrl-C, or a SIGTERM or SIGHUP sent to this process alone (``kill``, a supervisor), raises
    :class:`KeyboardInterrupt` in the block (:func:`~efficienttrack.core.stop_signals.stop_signals_as_interrupt`) and
    terminates the workers instead of waiting for them: without it they would run their jobs to the end, orphaned.

    Args:
        workers: processes at once.
    """
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"))
    try:
        with stop_signals_as_interrupt():
            yield pool
    except KeyboardInterrupt:
        # the pool keeps its processes in a private attribute; shutdown() can cancel queued work but not stop running work
        processes = list(pool._processes.values())
        for process in processes:
            process.terminate()
        for process in processes:
            process.join(timeout=5)
            if process.is_alive():  # one still starting up can miss the SIGTERM
                process.kill()
                process.join(timeout=5)
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    except BaseException:
        pool.shutdown(wait=True)
        raise
    pool.shutdown(wait=True)


def run_local(jobs: Sequence[Job], out: Path, workers: int, threads: int, on_done: Callable[[Outcome], None]) -> list[Outcome]:
    """Run the jobs here (``workers`` = 1) or in a pool of ``workers`` processes (:func:`process_pool`).

    A worker process that dies (killed, out of memory) breaks the pool, which fails every job it holds: those jobs
    run once more, each alone in a fresh worker, so that only the job that kills its worker again fails.

    Args:
        jobs: the jobs.
        out: the study folder.
        workers: processes at once; 1 runs the jobs one after the other in this process.
        threads: torch CPU threads of each job.
        on_done: called with each outcome as its job ends.

    Returns:
        The outcomes, in the order the jobs ended.
    """
    outcomes = []
    if workers == 1:
        for job in jobs:
            outcomes.append(execute(job, out, threads))
            on_done(outcomes[-1])
        return outcomes
    taken_down = []
    with process_pool(min(workers, len(jobs))) as pool:
        futures = {pool.submit(execute, job, out, threads): job for job in jobs}
        for future in as_completed(futures):
            try:
                outcome = future.result()
            except BrokenProcessPool:  # a worker died (killed, out of memory): the pool fails every job it holds
                taken_down.append(futures[future])
                continue
            except Exception as exc:
                outcome = Outcome(futures[future].name, None, f"its worker process failed: {type(exc).__name__}: {exc}")
            outcomes.append(outcome)
            on_done(outcome)
    # once more, each alone in a fresh worker: the job whose worker dies again fails by itself, the others finish
    for job in sorted(taken_down, key=lambda job: job.name):
        with process_pool(1) as pool:
            try:
                outcome = pool.submit(execute, job, out, threads).result()
            except Exception as exc:
                outcome = Outcome(job.name, None, f"its worker process failed twice: {type(exc).__name__}: {exc}")
        outcomes.append(outcome)
        on_done(outcome)
    return outcomes


def run_ray(
    jobs: Sequence[Job], out: Path, threads: int, address: str | None, num_cpus: int, on_done: Callable[[Outcome], None]
) -> list[Outcome]:
    """Run the jobs on Ray, one task per job: on the cluster at ``address``, or on a local instance started here.

    When this process is connected to Ray already (``ray.init`` was called), that instance is used and left running.
    Otherwise a local instance (``address`` None) gets ``num_cpus`` CPUs, a :data:`RAY_OBJECT_STORE_BYTES` object store
    and no dashboard, and is shut down at the end, as is the connection to a cluster. The jobs' folders must be on a
    file system the workers share with this process; a finished job's ``result.json`` is also written here from the
    task's result.

    Args:
        jobs: the jobs.
        out: the study folder (absolute, as the workers see it).
        threads: torch CPU threads of each job, and the CPUs its task asks Ray for.
        address: ``HOST:PORT`` of a running cluster's head node (``ray start --head``), or None.
        num_cpus: CPUs of a local instance.
        on_done: called with each outcome as its job ends.

    Returns:
        The outcomes, in the order the jobs ended.

    Raises:
        EfficientTrackError: Ray cannot connect to ``address`` or start a local instance.
    """
    import ray

    started = not ray.is_initialized()
    if started:
        local = {"num_cpus": num_cpus, "object_store_memory": RAY_OBJECT_STORE_BYTES, "include_dashboard": False}
        try:
            ray.init(**({"address": address} if address else local), logging_level=logging.WARNING, log_to_driver=False)
        except (ConnectionError, RuntimeError, ValueError) as exc:
            where = f"--address {address}: cannot connect to the Ray cluster" if address else "cannot start a local Ray"
            raise EfficientTrackError(f"{where}: {exc}") from exc
    outcomes = []
    try:
        task = ray.remote(num_cpus=max(threads, 1), max_retries=0)(execute)
        pending = {task.remote(job, out, threads): job for job in jobs}
        while pending:
            (ref,), _ = ray.wait(list(pending), num_returns=1)
            job = pending.pop(ref)
            try:
                outcome = ray.get(ref)
            except Exception as exc:  # the task or its worker died
                outcome = Outcome(job.name, None, f"its Ray task failed: {type(exc).__name__}: {str(exc).splitlines()[0]}")
            if outcome.result is not None and not (job_folder(out, job.name) / RESULT).exists():  # no shared file system
                write_json(job_folder(out, job.name) / RESULT, outcome.result)
            outcomes.append(outcome)
            on_done(outcome)
    finally:
        if started:
            ray.shutdown()
    return outcomes

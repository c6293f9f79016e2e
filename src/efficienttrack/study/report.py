"""A study's report, rebuilt from its jobs' folders every time: table (Markdown, CSV), ``study.json`` and the figure.

Each method and loop is reported at its final point: for each seed the last point of its curve, at the end of its
budget, so that nothing is chosen by looking at the test references; then the mean and the standard deviation over
the seeds (sample standard deviation; null with one seed) of that point's interaction steps (I.S.), interaction
time (I.T. = I.S. / 20 Hz, hours), wall time and every metric of :func:`~efficienttrack.data.metrics.compute_metrics`.
Beside it, two chosen points. The selected point, in a study with validation references
(:attr:`~efficienttrack.study.jobs.Study.validation`): for each seed the point of its curve with the lowest validation
MAE, and its test metrics; a choice made without the test references, so an honest figure for "trained until it
stopped improving". The best point: the point with the lowest test MAE, as the paper's Table I reports ("when the
model converges to the optimal value"); a choice made on the test set, so an optimistic figure, labelled so.

A study with validation references gets a second table under the first: each method and loop at each seed's selected
point, with every metric, as the first gives the final point. A study on the paper's simulator (``--system paper``)
prints the paper's Table I row under each of its rows, in both tables (:mod:`efficienttrack.study.paper_table`).

This module reads and writes a study's files (the jobs' results, :data:`BUNDLE`, the report's outputs) and combines
studies; the numbers are :mod:`~efficienttrack.study.summary`'s, the tables :mod:`~efficienttrack.study.tables`', the
figure :mod:`~efficienttrack.study.figure`'s.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import atomic_write, write_csv, write_json
from efficienttrack.study.figure import plot_study
from efficienttrack.study.jobs import ERROR, JOBS, RESULT, STUDY_CONFIG
from efficienttrack.study.methods import METHODS
from efficienttrack.study.paper_table import is_paper_system
from efficienttrack.study.summary import BEST_FIELDS, FIELDS, entry_key, summarize
from efficienttrack.study.tables import markdown_table

BUNDLE = "results.json"
"""The study's results as data (:func:`report`): what ``study-plot`` redraws the table and figure from."""
BUNDLE_FORMAT = "efficienttrack-study-results/1"
"""The ``format`` field of a :data:`BUNDLE`."""
OUTPUTS = (BUNDLE, "study.json", "study.md", "study.csv", "study.png")
"""The report's files in the study folder."""


@dataclass(frozen=True)
class Report:
    """A study's report.

    Attributes:
        entries: the content of ``study.json``, one entry per method and loop.
        failed: job name → error, of the jobs with an ``error.json`` and no result.
        markdown: the content of ``study.md``.
        paths: the files written.
    """

    entries: list[dict[str, Any]]
    failed: dict[str, str]
    markdown: str
    paths: tuple[Path, ...]


def read_result(path: Path) -> dict[str, Any] | None:
    """A job's ``result.json``, or None when it is missing or not a finished job's result (unreadable, truncated).

    Args:
        path: the file.

    Returns:
        The result (with ``method``, ``loop``, ``seed`` and a non-empty ``curve``), or None.
    """
    try:
        result = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return result if _is_result(result) else None


def _is_result(result: Any) -> bool:
    """Whether ``result`` is a finished job's result: a mapping with ``method``, ``loop``, ``seed`` and a curve."""
    keys = ("method", "loop", "seed", "curve")
    return isinstance(result, dict) and all(key in result for key in keys) and bool(result["curve"])


def read_bundle(path: Path) -> dict[str, Any]:
    """A study's results as data (``results.json``, :func:`report` writes it): what every table and figure is drawn from.

    Args:
        path: the file.

    Returns:
        ``{"format", "system", "jobs": [result.json of each finished job], "failed": {job: error}}``.

    Raises:
        EfficientTrackError: not such a file (unreadable, or another format).
    """
    try:
        bundle = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise EfficientTrackError(f"{path}: not a readable study results file ({exc})") from exc
    if not isinstance(bundle, dict) or bundle.get("format") != BUNDLE_FORMAT or not isinstance(bundle.get("jobs"), list):
        raise EfficientTrackError(f"{path}: not a study's {BUNDLE} (format '{BUNDLE_FORMAT}')")
    jobs = [job for job in bundle["jobs"] if _is_result(job)]
    if len(jobs) != len(bundle["jobs"]):
        raise EfficientTrackError(f"{path}: {len(bundle['jobs']) - len(jobs)} job(s) lack a method, loop, seed or curve")
    return bundle


def read_jobs(out: Path) -> tuple[list[dict[str, Any]], dict[str, str]]:
    """The finished jobs' results and the failed jobs' errors in a study folder, or in its results file.

    Args:
        out: the study folder (``out/jobs/<name>/result.json`` or ``error.json``), or its :data:`BUNDLE` file (a
            committed one, say, its folder long gone).

    Returns:
        The results (:func:`read_result`), in the order of the folders' names, and job name → error of the jobs with an
        ``error.json`` or an unreadable ``result.json``.

    Raises:
        EfficientTrackError: ``out`` holds no study (no ``jobs`` folder, not a results file).
    """
    if out.is_file():
        bundle = read_bundle(out)
        return bundle["jobs"], {str(k): str(v) for k, v in dict(bundle.get("failed") or {}).items()}
    if not (out / JOBS).is_dir():
        raise EfficientTrackError(f"{out}: no study here (no {JOBS}/ folder)")
    results, failed = [], {}
    for folder in sorted(path for path in (out / JOBS).iterdir() if path.is_dir()):
        result = read_result(folder / RESULT)
        if result is not None:
            results.append(result)
        elif (folder / RESULT).exists():  # named, never dropped: a report without it would look complete
            failed[folder.name] = f"unreadable {RESULT} (damaged or truncated): a rerun of the study runs the job again"
        elif (folder / ERROR).exists():
            try:
                failed[folder.name] = str(json.loads((folder / ERROR).read_text())["error"])
            except (OSError, ValueError, KeyError, TypeError):
                failed[folder.name] = f"unreadable {ERROR}"
    return results, failed


def _study_system(out: Path) -> dict[str, Any]:
    """The system a study folder (or results file) ran on, from its ``study_config.json`` (empty when it is missing)."""
    try:
        identity = json.loads((out if out.is_file() else out / STUDY_CONFIG).read_text())
    except (OSError, ValueError):
        return {}
    system = identity.get("system") if isinstance(identity, dict) else None
    return system if isinstance(system, dict) else {}


def report(out: str | Path) -> Report:
    """Rebuild the study's report from its jobs' folders: ``study.json``, ``study.md``, ``study.csv``, ``study.png``.

    It also writes the results as data, :data:`BUNDLE`: the study's identity and every job's curve (per seed and
    point: interaction steps, wall time, test and validation metrics; the job's settings changes and provenance, with
    the commit), from which ``study-plot`` redraws the table and the figure without the folder.

    Args:
        out: the study folder (``out/jobs/<name>/result.json`` of each finished job).

    Returns:
        The report.

    Raises:
        EfficientTrackError: ``out`` holds no study (no ``jobs`` folder).
    """
    out = Path(out)
    results, failed = read_jobs(out)
    entries = summarize(results)
    paper = is_paper_system(_study_system(out))
    markdown = markdown_table(entries, failed, paper)
    fields = (*FIELDS, *(f"{which}_{field}" for which in ("selected", "best") for field in BEST_FIELDS))
    header = ["method", "loop", "seeds", *(name for field in fields for name in (field, f"{field}_std")), "settings_changes"]
    rows = (
        [e["method"], e["loop"], " ".join(map(str, e["seeds"])), *(e[name] for name in header[3:-1]),
         " ".join(e.get("settings_changes", ()))]
        for e in entries
    )  # fmt: skip
    identity = json.loads((out / STUDY_CONFIG).read_text()) if (out / STUDY_CONFIG).is_file() else {}
    bundle = {"format": BUNDLE_FORMAT, "system": _study_system(out), "study": identity, "jobs": results, "failed": failed}
    paths = (
        write_json(out / BUNDLE, bundle),
        write_json(out / "study.json", entries),
        atomic_write(out / "study.md", lambda f: f.write(markdown), mode="w"),
        write_csv(out / "study.csv", header, rows),
        plot_study(entries, out / "study.png", paper),
    )
    return Report(entries, failed, markdown, paths)


def _same_measurement(result: dict[str, Any], held: dict[str, Any]) -> bool:
    """Whether two jobs' results are one measurement of a method that ignores the seed: the same test figures."""
    method = METHODS.get(result["method"])
    if method is None or method.seeded:
        return False
    return [p["metrics"] for p in result["curve"]] == [p["metrics"] for p in held["curve"]]


def _longer_note(job: str, kept: tuple[Path, dict[str, Any]], dropped: tuple[Path, dict[str, Any]]) -> str:
    """The table's note on a job found in two folders at two budgets: which (folder, result) is shown."""
    return f"{job}: {kept[0]}'s {kept[1]['budget']:,} steps in place of {dropped[0]}'s {dropped[1]['budget']:,}"


def combine(folders: Sequence[str | Path], path: str | Path) -> Report:
    """One table and one figure of several study folders (studies of one system run in several sittings).

    Args:
        folders: study folders (each ``jobs/<name>/result.json``); a method, loop and seed may be in one of them only,
            except for a method whose outcome does not depend on the seed (PD, the ILC oracle): a job of it found again,
            at any seed, with the same test figures is the same measurement, taken once; and a job run again with a
            larger budget (a longer run of it), which takes the shorter one's place, as the table notes.
        path: the PNG to write (:func:`~efficienttrack.study.figure.plot_study`).

    Returns:
        The combined report (its ``paths``: the figure alone).

    Raises:
        EfficientTrackError: a folder holds no study, two folders ran on different systems, or one job (method, loop,
            seed) is in two folders at one budget.
    """
    results: list[dict[str, Any]] = []
    failed: dict[str, str] = {}
    longer: list[str] = []
    owner: dict[tuple[str, str, tuple[str, ...], int], tuple[Path, dict[str, Any]]] = {}
    system: tuple[Path, dict[str, Any]] | None = None
    for folder in map(Path, folders):
        found, errors = read_jobs(folder)
        here = _study_system(folder)
        if system is not None and here != system[1]:
            raise EfficientTrackError(
                f"{folder}: ran on {here or 'an unknown system'}, {system[0]} on {system[1]}: one system only"
            )
        system = system or (folder, here)
        for result in found:
            seeded = result["method"] not in METHODS or METHODS[result["method"]].seeded
            key = (*entry_key(result), result["seed"] if seeded else -1)
            if key in owner:
                first, held = owner[key]
                if _same_measurement(result, held):
                    continue
                job = f"{result['method']}-{result['loop']}-s{result['seed']}"
                budgets = (result.get("budget"), held.get("budget"))
                if budgets[0] == budgets[1] or None in budgets:  # not a longer run of it: the same job twice
                    raise EfficientTrackError(f"{folder} and {first} both hold {job}: give it once")
                if held["budget"] > result["budget"]:
                    longer.append(_longer_note(job, (first, held), (folder, result)))
                    continue
                longer.append(_longer_note(job, (folder, result), (first, held)))
                results = [r for r in results if r is not held]
            owner[key] = (folder, result)
            results.append(result)
        failed |= {f"{folder}/{name}": error for name, error in errors.items()}
    entries = summarize(results)
    paper = system is not None and is_paper_system(system[1])
    markdown = markdown_table(entries, failed, paper)
    if longer:
        markdown += "\nJobs run again with a larger budget, the longer run shown: " + "; ".join(longer) + ".\n"
    return Report(entries, failed, markdown, (plot_study(entries, path, paper),))

"""The fixed-rate loop over a folder of references (``efficienttrack deploy``), and the simulator as a machine.

:func:`deploy` runs :class:`~efficienttrack.deploy.loop.Loop` along each reference in turn, one machine opened per reference,
each with its own per-tick log ``OUT/<reference>.jsonl``, and keeps ``OUT/deploy.json`` (the settings and one summary
per finished run) up to date after every run. A run that a watchdog stopped ends the deployment: the references after
it are not started. After each run its log is also written as episode records (:func:`records_from_log`,
``OUT/records/``), the data of the next continual-learning round (``efficienttrack round --data OUT/records``).

The machine is either the simulator (:class:`SimulatedMachine` around a system of :mod:`efficienttrack.systems.spec`,
the built-in ``xe75`` by default, reset at each reference's start) or a user's adapter (:func:`load_machine`, an import
path ``module:callable`` returning a :class:`~efficienttrack.deploy.loop.Machine`).
"""

from __future__ import annotations

import inspect
import json
import math
import sys
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from efficienttrack.core.angles import wrap
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import write_json
from efficienttrack.core.joints import DT, JOINT_NAMES, SWING
from efficienttrack.core.provenance import differences
from efficienttrack.data.cycles import joint_move
from efficienttrack.data.metrics import MIN_STEPS, compute_metrics
from efficienttrack.data.records import EpisodeRecord, load_records
from efficienttrack.data.references import Reference
from efficienttrack.deploy.guard import GuardedRuntime
from efficienttrack.deploy.loop import Loop, LoopConfig, LoopResult, LoopRuntime, NotAtStart, TickLog, set_aside
from efficienttrack.deploy.machine import MONOTONIC, Clock, Machine, SimulatedClock, SimulatedMachine
from efficienttrack.systems.limits import GuardLimits
from efficienttrack.systems.spec import SystemSpec, load_callable

DEPLOY_JSON = "deploy.json"
"""The settings and the summaries of a deployment's runs, in its output folder."""
DEPLOY_RECORDS = "records"
"""Folder of the episode records made from the runs' logs, in a deployment's output folder."""
DEPLOY_OUTPUTS = (DEPLOY_JSON, "*.jsonl", DEPLOY_RECORDS)
"""What ``deploy`` writes in its output folder (what ``--force`` clears)."""
UNUSABLE_TICK_EVENTS = frozenset({"dropped", "nonfinite", "stale"})
"""Loop events of a tick whose reading is missing or old: no record row (:func:`records_from_log`)."""


SHADOW_JSON = "shadow.json"
"""Where an export folder keeps its passing shadow deployment (:func:`record_shadow`; a checkpoint keeps it in its JSON)."""
BETWEEN_EPISODES = ("approach", "prompt", "stop")
"""What happens when the machine is not at a reference's start: a slow approach through the loop, the operator asked to
bring it there (:func:`ask_operator`), or a stop."""
APPROACH_SPEED = 0.1
"""rad/s, the peak speed of the joint that moves farthest on an approach (the others slower, all arriving together)."""
APPROACH_HOLD = 2.0
"""s an approach holds the reference's start, for the position controller to settle there."""
APPROACH_PUSH = 1.0
"""Gain of an approach's adjustment, a = gain × (q*_{t+1} − q_t) within the limits: it pushes a position controller with
a dead band or a slow settling the rest of the way (the xe75's swing stops 0.14 rad short of a start without it)."""
APPROACH_TRIES = 3
"""Approaches to one reference's start before the episode is given up (the loop's refusal is the error)."""


def approach_path(q_from: np.ndarray, q_to: np.ndarray, dt: float = DT) -> np.ndarray:
    """The references of an approach: a :func:`~efficienttrack.data.cycles.joint_move`, then a hold.

    The move peaks at :data:`APPROACH_SPEED`; the hold lasts :data:`APPROACH_HOLD`.

    Args:
        q_from: (4,) rad, where the machine stands.
        q_to: (4,) rad, where it should be (a reference's start).
        dt: s, the control period.

    Returns:
        (L, 4) rad: ``q_from`` … ``q_to``, then :data:`APPROACH_HOLD` s of ``q_to``.
    """
    path = np.concatenate([np.asarray(q_from, dtype=np.float64)[None], joint_move(q_from, q_to, APPROACH_SPEED, dt)])
    return np.concatenate([path, np.repeat(path[-1:], int(round(APPROACH_HOLD / dt)), axis=0)])


def approach(
    ref: Reference, away: NotAtStart, make_machine: Callable[[Reference], Machine], limits: GuardLimits, cfg: LoopConfig,
    clock: Clock, logs: Path,
) -> LoopResult:  # fmt: skip
    """Bring the machine from where the refused start found it to ``ref``'s start, through the guarded loop (a = 0).

    The approach sends :func:`approach_path`, each reference pushed by :data:`APPROACH_PUSH`, through the same guard
    and watchdogs as an episode; it is logged as ``logs/approach/<reference>.jsonl`` (an earlier try's set aside), never
    made into records (it is not scored or trained on).

    Args:
        ref: the reference whose start to reach.
        away: the loop's refusal to start ``ref`` (where the machine stood).
        make_machine: reference → a new adapter.
        limits: the machine's limits.
        cfg: the loop's timing and watchdogs.
        clock: the loop's clock.
        logs: the folder of the episodes' logs.

    Returns:
        The approach's result (``stopped`` when a watchdog ended it).
    """
    folder = logs / "approach"
    folder.mkdir(parents=True, exist_ok=True)
    log_path = folder / f"{ref.name}.jsonl"
    set_aside(log_path)
    runtime = GuardedRuntime(_push, (1, 1), None, limits, cfg.dt)
    with TickLog(log_path, cfg.fsync_every) as log:
        path = approach_path(away.position, ref.q[0], cfg.dt)
        return Loop(runtime, make_machine(ref), limits, cfg, clock, log).run(path, f"{ref.name} (approach)")


def ask_operator(ref: Reference, away: NotAtStart, ask: Callable[[str], str] = input) -> bool:
    """Ask the operator to bring the machine to ``ref``'s start by hand (``--between-episodes prompt``).

    Args:
        ref: the reference whose start the machine missed.
        away: the loop's refusal, with where the machine stands.
        ask: shows the question and returns the answer (``input``; a test gives its own).

    Returns:
        True to try the episode again (Enter), False to stop (``q``, or no operator: end of input).
    """
    go = ref.q[0] - away.position
    go[SWING] = wrap(go[SWING])
    degrees = ", ".join(f"{joint} {math.degrees(v):.1f}°" for joint, v in zip(JOINT_NAMES, ref.q[0], strict=True))
    to_go = ", ".join(f"{joint} {math.degrees(v):+.1f}°" for joint, v in zip(JOINT_NAMES, go, strict=True))
    try:
        answer = ask(f"{ref.name}: bring the machine to the start ({degrees}; to go: {to_go}), then press Enter (q to stop): ")
    except EOFError:
        return False
    return answer.strip().lower() not in ("q", "quit", "stop")


def run_episode(
    ref: Reference,
    run: Callable[[], LoopResult],
    between: str,
    make_machine: Callable[[Reference], Machine],
    limits: GuardLimits,
    cfg: LoopConfig,
    clock: Clock,
    logs: Path,
    ask: Callable[[str], str] = input,
) -> LoopResult:
    """``run()`` (the loop along ``ref``); when the machine is not at its start, bring it there first (``between``).

    Args:
        ref: the reference.
        run: runs the episode's loop (opens its log and adapter).
        between: ``"approach"`` (:func:`approach`, then the episode), ``"prompt"`` (:func:`ask_operator`, then the
            episode) or ``"stop"`` (the refusal is the error); after :data:`APPROACH_TRIES` the refusal is the error.
        make_machine: reference → a new adapter.
        limits: the machine's limits.
        cfg: the loop's timing and watchdogs.
        clock: the loop's clock.
        logs: the folder of the episodes' logs (the approach's go to ``logs/approach``).
        ask: with ``"prompt"``: how the operator is asked (``input``).

    Returns:
        The episode's result, or the approach's when a watchdog stopped it (the episode did not run).
    """
    for tries in range(APPROACH_TRIES + 1):
        try:
            return run()
        except NotAtStart as away:
            if between == "stop" or tries == APPROACH_TRIES:
                raise
            if between == "prompt":
                if not ask_operator(ref, away, ask):
                    raise
                continue
            gap = np.abs(away.position - ref.q[0])
            gap[SWING] = abs(wrap(gap[SWING]))
            log = logs / "approach" / f"{ref.name}.jsonl"  # the machine moves unasked for by a reference: say so
            print(f"{ref.name}: the machine stands {gap.max():.3f} rad from the start; approaching it through the loop "
                  f"(try {tries + 1} of {APPROACH_TRIES}; log {log})", file=sys.stderr)  # fmt: skip
            approached = approach(ref, away, make_machine, limits, cfg, clock, logs)
            if approached.stopped:
                return approached
    raise AssertionError("unreachable: the last try returns or raises")


def _push(obs_hist: np.ndarray, qref_hist: np.ndarray, q_des_future: np.ndarray) -> np.ndarray:
    """An approach's adjustment (:data:`~efficienttrack.deploy.guard.PolicyCall`): towards the path, ahead of the lag."""
    error = q_des_future[:, 0] - obs_hist[:, -1, :4]
    error[:, SWING] = wrap(error[:, SWING])
    return APPROACH_PUSH * error


def load_machine(spec: str, options: dict[str, Any], clock: Clock = MONOTONIC) -> Callable[[Reference], Machine]:
    """A user's machine adapter by import path: a factory of one adapter per reference.

    Args:
        spec: ``"module.path:callable"``; the callable is called with ``options`` and returns a
            :class:`~efficienttrack.deploy.machine.Machine` (a context manager with ``read`` and ``send``).
        options: its keyword options (``--machine-opt key=value``).
        clock: the loop's clock, passed as ``clock=`` to a callable that takes one (a simulated machine).

    Returns:
        reference → a new adapter (the reference is not passed on: a real machine starts where it stands).
    """
    factory = load_callable(spec, "machine")
    if takes_clock(factory):
        options = {**options, "clock": clock}

    def make(ref: Reference) -> Machine:
        try:
            machine = factory(**options)
        except TypeError as exc:
            raise EfficientTrackError(f"machine '{spec}': cannot be built with options {options}: {exc}") from exc
        except EfficientTrackError:
            raise
        except Exception as exc:  # the user's adapter failed to connect or to start: say so in one line, nothing was sent
            raise EfficientTrackError(
                f"machine '{spec}': building the adapter failed ({type(exc).__name__}: {exc}); nothing was sent"
            ) from exc
        missing = [name for name in ("__enter__", "__exit__", "read", "send") if not hasattr(machine, name)]
        if missing:
            raise EfficientTrackError(
                f"machine '{spec}': the adapter has no {', '.join(missing)} (see efficienttrack.deploy.machine.Machine)"
            )
        return machine

    return make


def deploy(
    references: Sequence[Reference],
    runtime: LoopRuntime,
    make_machine: Callable[[Reference], Machine],
    limits: GuardLimits,
    out: str | Path,
    cfg: LoopConfig | None = None,
    clock: Clock = MONOTONIC,
    shadow: bool = False,
    settings: dict[str, Any] | None = None,
    on_done: Callable[[LoopResult], None] | None = None,
    between: str = "approach",
) -> list[LoopResult]:
    """Run the loop along each reference in turn; stop at the first run a watchdog stopped.

    Args:
        references: the references (``.name``, ``.q`` (L, 4) rad), each checked against ``limits`` before anything moves.
        runtime: the runtime, started afresh for each reference.
        make_machine: reference → its machine adapter (opened and closed by the loop).
        limits: the machine's limits (joint limits of every reference sent, the rate of the adjustment).
        out: the output folder (created): ``<reference>.jsonl`` per run, :data:`DEPLOY_JSON`, and the runs' episode
            records in :data:`DEPLOY_RECORDS` (:func:`records_from_log`); :data:`DEPLOY_JSON` holds their tracking
            metrics (:func:`deployed_tracking`).
        cfg: the loop's timing and watchdogs.
        clock: the loop's clock.
        shadow: send the raw reference; only log the adjustment.
        settings: what to record in :data:`DEPLOY_JSON` besides the loop's settings (the policy, the system, …).
        on_done: called with each run's result as soon as it ends.
        between: when the machine is not at a reference's start: ``"approach"`` it slowly through the loop first
            (logged in ``out/approach``), or ``"stop"``.

    Returns:
        One result per run started (the last one stopped early when ``results[-1].stopped``); none when every run was
        done earlier.

    Raises:
        EfficientTrackError: ``out`` holds a deployment with other settings (:func:`finished_runs`).
    """
    cfg = LoopConfig() if cfg is None else cfg
    for ref in references:
        limits.check_reference(ref.q, ref.name)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    results: list[LoopResult] = []
    header = json.loads(json.dumps({**(settings or {}), "shadow": shadow, "loop": vars(cfg), "limits": limits.to_dict()}))
    done = finished_runs(out, header)
    for ref in references:
        if ref.name in done:
            continue
        log_path = out / f"{ref.name}.jsonl"
        aside = set_aside(log_path)
        if aside is not None:  # the earlier try's records go by the name its log now has
            _rename_run_records(log_path, aside, out / DEPLOY_RECORDS, shadow)

        def run(ref: Reference = ref, log_path: Path = log_path) -> LoopResult:
            with TickLog(log_path, cfg.fsync_every) as log:
                return Loop(runtime, make_machine(ref), limits, cfg, clock, log, shadow).run(ref.q, ref.name)

        result = run_episode(ref, run, between, make_machine, limits, cfg, clock, out)
        results.append(result)
        if log_path.exists():
            _save_run_records(log_path, out / DEPLOY_RECORDS, shadow)
        summaries = {**done, **{r.name: r.summary() for r in results}}
        runs = [summaries[r.name] for r in references if r.name in summaries]
        write_json(out / DEPLOY_JSON, {**header, "runs": runs, "tracking": deployed_tracking(out)})
        if on_done is not None:
            on_done(result)
        if result.stopped:
            break
    return results


def finished_runs(out: Path, header: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """The runs an earlier deployment into ``out`` finished, which a rerun with the same settings does not repeat.

    Args:
        out: the deployment's output folder.
        header: this deployment's settings, as :data:`DEPLOY_JSON` holds them (without ``runs`` and ``tracking``).

    Returns:
        Reference name → its run's summary, for the runs that ran to their end (``reason`` ``done``).

    Raises:
        EfficientTrackError: :data:`DEPLOY_JSON` is unreadable, or records other settings (naming the fields).
    """
    path = out / DEPLOY_JSON
    if not path.exists():
        return {}
    try:
        earlier = json.loads(path.read_text())
        runs = [run for run in earlier["runs"] if run["reason"] == "done"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise EfficientTrackError(f"{path}: cannot be read ({exc!r}); use another --out, or --force to start afresh") from exc
    changed = differences({key: earlier.get(key) for key in header}, header)
    if changed:
        raise EfficientTrackError(
            f"{path}: a deployment with other settings ({'; '.join(changed[:3])}); use another --out, or --force to start "
            "afresh"
        )
    return {run["name"]: run for run in runs}


def _rename_run_records(log: Path, aside: Path, folder: Path, shadow: bool) -> None:
    """The records of the run logged in ``log`` (now ``aside``) renamed after ``aside``, so that a new run's keep theirs."""
    folder.mkdir(exist_ok=True)
    for record in records_from_log(aside, shadow):
        stale = folder / f"{log.stem}{record.meta['name'].removeprefix(aside.stem)}.npz"
        record.save(folder / f"{record.meta['name']}.npz")
        stale.unlink(missing_ok=True)


def deployed_tracking(out: str | Path) -> dict[str, Any] | None:
    """The paper's metrics (:func:`~efficienttrack.data.metrics.compute_metrics`) of a deployment's records so far.

    In shadow mode they are the position controller's own tracking, armed the policy's: the two side by side are the
    machine's evaluation.

    Args:
        out: the deployment's output folder.

    Returns:
        The metrics, or None while no record is long enough to measure.
    """
    folder = Path(out) / DEPLOY_RECORDS
    records = [r for r in load_records(folder) if len(r) >= MIN_STEPS] if folder.is_dir() else []
    return compute_metrics(records) if records else None


def records_from_log(path: str | Path, shadow: bool | None = None) -> list[EpisodeRecord]:
    """The episode records of one run's tick log (``OUT/<reference>.jsonl``), to train the next round on.

    Row k of a record is tick k of the run: ``q``, ``qd`` of its reading, ``q_ref`` the reference the machine took,
    ``q_des`` = q*_{k+1}, ``t`` its deadline (s after the start), ``u`` None. ``meta["guard"]`` and
    ``meta["loop_events"]`` give, per guard reason and loop event (``ramped``, ``hold``, ``fallback``, …), the rows it
    happened at, as :func:`~efficienttrack.deploy.episodes.rollout`'s records do for the guard.

    Only ticks on the 20 Hz grid with a fresh reading make rows: a tick whose reading was missing, not finite or old
    (:data:`UNUSABLE_TICK_EVENTS`), or that follows skipped periods, ends a record, and the next usable tick starts
    another. Records are named after the reference, the second and later ones ``<reference>-2``, ``-3``, …; stretches
    shorter than 2 ticks are dropped. A log cut short by a crash gives the ticks it has (a last line cut in the middle
    is left out).

    Args:
        path: the run's log.
        shadow: whether the run was in shadow mode (the raw reference sent), kept in each record's meta; None: unknown.

    Returns:
        The records, in the order of their ticks (none when no two usable ticks follow each other).

    Raises:
        EfficientTrackError: the file cannot be read, a line before the last is not JSON, or a line is not a tick's
            (fields missing or of the wrong kind), or a record has non-finite values.
    """
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise EfficientTrackError(f"{path}: cannot read the tick log ({exc})") from exc
    ticks = []
    for number, line in enumerate(lines, 1):
        try:
            entry = json.loads(line)
        except json.JSONDecodeError as exc:
            if number == len(lines):  # the line a crash cut short
                break
            raise EfficientTrackError(f"{path}: line {number} is not JSON ({exc.msg}): not a deploy tick log?") from exc
        if isinstance(entry, dict) and "event" in entry:
            continue
        ticks.append(_checked_tick(entry, f"{path}: line {number}"))
    name = path.stem
    stretches: list[list[dict[str, Any]]] = []
    current: list[dict[str, Any]] = []
    for entry in ticks:
        if current and entry["tick"] != current[-1]["tick"] + 1:  # whole periods were skipped
            stretches.append(current)
            current = []
        if UNUSABLE_TICK_EVENTS & set(entry["events"]) or None in entry["obs"]:
            stretches.append(current)
            current = []
            continue
        current.append(entry)
    stretches.append(current)
    records: list[EpisodeRecord] = []
    for stretch in (part for part in stretches if len(part) >= 2):
        label = name if not records else f"{name}-{len(records) + 1}"
        obs = np.array([entry["obs"] for entry in stretch], dtype=np.float64)
        meta = {
            "name": label,
            "reference": name,
            "source": "deploy",
            "first_tick": stretch[0]["tick"],
            "shadow": shadow,
            "guard": _rows_with(stretch, "guard"),
            "loop_events": _rows_with(stretch, "events"),
        }
        record = EpisodeRecord(
            q=obs[:, :4],
            qd=obs[:, 4:],
            q_ref=np.array([entry["q_ref"] for entry in stretch], dtype=np.float64),
            q_des=np.array([entry["q_des"] for entry in stretch], dtype=np.float64),
            u=None,
            t=np.array([entry["t"] for entry in stretch], dtype=np.float64),
            meta=meta,
        )
        records.append(record.validate(f"{path} (ticks {stretch[0]['tick']}–{stretch[-1]['tick']})"))
    return records


def _rows_with(stretch: list[dict[str, Any]], key: str) -> dict[str, list[int]]:
    """Name → the rows of ``stretch`` whose ``key`` list holds it (the runtime's guard reasons, the loop's events).

    The events of a whole run (``start``, ``shadow``: the record's meta says so) are left out; a log without ``key``
    gives none.
    """
    rows: dict[str, list[int]] = {}
    for row, entry in enumerate(stretch):
        for name in entry.get(key) or ():
            if isinstance(name, str) and name not in ("start", "shadow"):
                rows.setdefault(name, []).append(row)
    return rows


TICK_VECTORS = {"obs": 8, "q_ref": 4, "q_des": 4}
"""The vectors of a tick log's line that make a record row, and their lengths."""


def _checked_tick(entry: Any, source: str) -> dict[str, Any]:
    """A tick log's line with what a record row needs (numbers or nulls), else EfficientTrackError naming ``source``."""
    if not isinstance(entry, dict):
        raise EfficientTrackError(f"{source} is not a JSON object: not a deploy tick log?")
    missing = [key for key in ("tick", "t", "events", *TICK_VECTORS) if key not in entry]
    if missing:
        raise EfficientTrackError(f"{source} has no {', '.join(missing)}: not a deploy tick log?")
    for key, length in TICK_VECTORS.items():
        value = entry[key]
        if not (isinstance(value, list) and len(value) == length and all(_number_or_null(v) for v in value)):
            raise EfficientTrackError(f"{source}: field '{key}' must be {length} numbers (or nulls), got {value!r:.80}")
    if not (_number_or_null(entry["t"]) and isinstance(entry["tick"], int) and isinstance(entry["events"], list)):
        raise EfficientTrackError(f"{source}: fields 'tick', 't', 'events' must be an integer, a number and a list")
    return entry


def _number_or_null(value: Any) -> bool:
    return value is None or (isinstance(value, int | float) and not isinstance(value, bool))


def _save_run_records(log: Path, folder: Path, shadow: bool) -> None:
    """Write a finished run's records (:func:`records_from_log`) into ``folder``; a log that gives none only warns."""
    try:
        records = records_from_log(log, shadow)
    except EfficientTrackError as exc:  # the run is over and its log kept: say why, go on with the next reference
        warnings.warn(f"no episode records from {log.name}: {exc}", stacklevel=2)
        return
    if not records:
        warnings.warn(f"no episode records from {log.name}: no two usable ticks in a row", stacklevel=2)
        return
    folder.mkdir(exist_ok=True)
    for record in records:
        record.save(folder / f"{record.meta['name']}.npz")


def recorded_verdict(policy: str | Path | None) -> str | None:
    """The ``worse_than_pd`` warning of the last evaluation of ``policy``, when it tracked worse than PD.

    The policy's own record comes first: a run or ``evaluate`` keeps it in the checkpoint's JSON config
    (``"evaluation"``), and an export carries it in its contract (``source.evaluation``), so a copy or an export is
    judged like the original. Without one, the run that tested it: a run writes ``metrics.json`` with the path of the
    policy it evaluated (its own folder, or two levels up for a later round's policy in ``OUT/rounds/<k>/``).

    Args:
        policy: the policy deployed (a ``policy.pt`` or an export folder), or None.

    Returns:
        The warning, or None when the policy tracked as well as PD or better, or no run that tested it is found.
    """
    if policy is None:
        return None
    path = Path(policy).resolve()
    record = _own_record(path, "evaluation") or _testing_run(path)
    verdict = None if record is None else record.get("worse_than_pd")
    return verdict if isinstance(verdict, str) else None


def proven(policy: str | Path) -> bool:
    """Whether anything shows how ``policy`` behaves: an evaluation, or a shadow deployment run to its end.

    The evaluation is the policy's own record or the run's that tested it (:func:`recorded_verdict`), the shadow
    deployment one that ran every reference (:func:`record_shadow`). A policy without either is unproven.

    Args:
        policy: a ``policy.pt`` or an export folder.
    """
    path = Path(policy).resolve()
    return any(
        record is not None for record in (_own_record(path, "evaluation"), _own_record(path, "shadow"), _testing_run(path))
    )


def record_shadow(policy: str | Path, facts: dict[str, Any]) -> None:
    """Keep a passing shadow deployment with the policy: in its JSON config (``"shadow"``), or ``shadow.json`` in an export.

    Args:
        policy: the policy deployed (a ``policy.pt`` or an export folder).
        facts: what the shadow deployment was (its folder, runs, machine, when).

    Raises:
        EfficientTrackError: the record cannot be written (a read-only copy).
    """
    path = Path(policy)
    target = path / SHADOW_JSON if path.is_dir() else path.with_suffix(".json")
    try:
        meta = {} if path.is_dir() else json.loads(target.read_text())
        write_json(target, {**meta, "shadow": facts})
    except (OSError, ValueError) as exc:
        raise EfficientTrackError(f"{target}: cannot record the shadow deployment with the policy ({exc})") from exc


def _testing_run(path: Path) -> dict[str, Any] | None:
    """The ``metrics.json`` of the run that evaluated the policy at ``path`` (its folder or two levels up), or None."""
    for folder in list(path.parents)[:3]:
        try:
            metrics = json.loads((folder / "metrics.json").read_text())
        except (OSError, ValueError):
            continue
        tested = metrics.get("policy") if isinstance(metrics, dict) else None
        inside = (folder.name, *path.relative_to(folder).parts)  # the run wrote the path as given: compare from OUT on
        if isinstance(tested, str) and Path(tested).parts[-len(inside) :] == inside:
            return metrics
    return None


def _own_record(path: Path, key: str) -> dict[str, Any] | None:
    """What a checkpoint's JSON (or an export's contract ``source``, or its ``shadow.json``) records under ``key``."""
    if path.is_dir():  # an export, run by ONNX Runtime: its module's import is needed to deploy it anyway
        from efficienttrack.deploy.onnx_runtime import CONTRACT_FILE

        meta = path / (SHADOW_JSON if key == "shadow" else CONTRACT_FILE)
    else:
        meta = path.with_suffix(".json")
    try:
        data = json.loads(meta.read_text())
    except (OSError, ValueError):
        return None
    if path.is_dir() and key != "shadow":
        data = data.get("source") if isinstance(data, dict) else None
    record = data.get(key) if isinstance(data, dict) else None
    return record if isinstance(record, dict) else None


def machine_parts(
    spec: SystemSpec, machine: str | None, machine_options: dict[str, Any], fast: bool
) -> tuple[Callable[[Reference], Machine], GuardLimits, Clock]:
    """The machine that ``deploy`` and ``collect`` drive through the loop: its factory, its limits and the clock.

    Args:
        spec: the simulated system (used when ``machine`` is None); with ``machine``, only its limits file counts.
        machine: a user's adapter ``module:callable``, or None for the simulator.
        machine_options: the adapter's keyword options.
        fast: run the simulator on a simulated clock, as fast as it computes (refused for a user's machine).

    Returns:
        Reference → machine adapter (a simulator is reset at the reference's start), the machine's limits, the clock.
    """
    if machine is not None:
        clock: Clock = SimulatedClock() if fast else MONOTONIC
        if fast and not takes_clock(load_callable(machine, "machine")):
            raise EfficientTrackError(
                "--fast runs on a simulated clock, which a real machine does not keep: it runs in real time only (a "
                "simulated machine that takes the loop's clock, such as efficienttrack.deploy.machine:simulated, may)"
            )
        if spec.limits is None:
            raise EfficientTrackError("--machine needs --limits FILE: the joint limits and adjustment bounds of that machine")
        if spec.system is not None or spec.plant is not None:
            raise EfficientTrackError("give --machine SPEC or a simulated --system/--plant, not both")
        return load_machine(machine, machine_options, clock), GuardLimits.load(spec.limits), clock
    system = spec.open()
    if system.dt != DT:
        raise EfficientTrackError(f"{system.name}: runs at dt = {system.dt} s; the loop runs at {DT} s (20 Hz)")
    clock = SimulatedClock() if fast else MONOTONIC

    def make_machine(ref: Reference) -> Machine:
        return SimulatedMachine(system, ref.q[0], clock)

    return make_machine, system.limits, clock


def takes_clock(factory: Callable[..., Any]) -> bool:
    """Whether a machine factory keeps the loop's time (a simulated machine): it has a ``clock`` parameter."""
    try:
        return "clock" in inspect.signature(factory).parameters
    except (TypeError, ValueError):  # a builtin or C callable without a signature
        return False


def policy_runtime(policy: str | Path | None, limits: GuardLimits, device: str) -> LoopRuntime:
    """The runtime that ``deploy`` runs a policy in.

    Args:
        policy: a policy checkpoint (``policy.pt``, run by the torch runtime), an export folder (``policy.onnx`` and
            ``policy.json`` of ``efficienttrack export``, run by the torch-free
            :class:`~efficienttrack.deploy.onnx_runtime.OnnxRuntime` on the CPU), or None for the raw reference alone (a = 0).
        limits: the machine's limits, for the runtime's guard.
        device: where a checkpoint runs (an export runs on the CPU).
    """
    if policy is not None and Path(policy).is_dir():
        from efficienttrack.deploy.onnx_runtime import OnnxRuntime, load_onnx_policy

        exported = load_onnx_policy(policy)
        if exported.contract.dt != DT:
            raise EfficientTrackError(
                f"{policy}: the export was made for dt = {exported.contract.dt} s; the loop runs at {DT} s (20 Hz)"
            )
        return OnnxRuntime(exported, limits=limits)
    from efficienttrack.deploy.runtime import Runtime
    from efficienttrack.learn.policy import load_policy  # torch: only here, the loop itself runs without it

    return Runtime(None if policy is None else load_policy(policy, device), limits=limits)

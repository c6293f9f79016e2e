"""An ORACLE lower bound, not a competitor: iterative learning control (ILC) on each test reference itself.

ILC repeats the same reference many times and corrects the reference sent from the previous trial's error. Trial
k sends, on the closed loop (the machine's own position controller),

    q^r_k(t+1) = clamp(q*(t+1) + a_k(t)),     a_0 = 0 (trial 0 is the PD controller alone),

and learns from the tracking error e_k(s) = wrap(q*(s) − q_k(s)) of the trial it has just run:

    a_{k+1}(t) = clip(Q[a_k(t) + L · e_k(t + 1 + δ)], ±max_adjust),

with L a learning gain per joint, δ the lead per joint (steps the machine answers later than the step after the
reference is sent; by default identified from trial 0, :func:`identify_lead`), Q a zero-phase low-pass over time (a
Butterworth filter run forwards and backwards, ``scipy.signal.filtfilt``; it keeps the high-frequency part of the error,
which the machine cannot follow, from building up trial after trial), clip the system's adjustment bound
(``limits.max_adjust``) and clamp its joint limits, as the environments apply an action. The error past the end of a
reference is unknown and taken as zero.

It is an oracle: it runs on the held-out test references and learns a correction for each of them, so it sees
exactly what the fair methods are scored on and never generalizes to a new reference. Its curve says how much
tracking error any reference adjustment can remove on this system (within the adjustment bound): the error left to
win. It has the closed loop only: on the open loop (PWM sent to the plant) a pure feed-forward correction of a
hydraulic integrator without feedback drifts trial after trial, which no fair comparison needs.

On top of a policy (``train_ilc(..., policy=PATH)``) each trial deploys a trained adjustment policy through the guarded
runtime and adds the learned correction to its adjustment, within the same bound:

    q^r_k(t+1) = clamp(q*(t+1) + clip(π(o_H, q^r_H, q*_F) + a_k(t), ±max_adjust)),      a_0 = 0,

the policy's history holding its own references, as it was trained and is deployed: the correction is a feed-forward
it does not see, and the loop the ILC learns on is the deployed one. (With the correction in its history, as sent, the
policy answered it and the oracle ended higher on two plants of three, docs/ilc.md.) Trial 0 is then the policy alone,
and the lead is identified from its run. Where the update law by itself stops above what a policy reaches (a delay and
a dead band), the policy's feedback and the correction's feed-forward together go lower: each trial is still a run of
the true system, so its figure still bounds the limit from above.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from contextlib import nullcontext
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy.signal import butter, filtfilt

from efficienttrack.baselines.curve import CURVE_FILE, CurveRecorder, TrainingRun, check_training_run
from efficienttrack.core.angles import wrap
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import output_lock
from efficienttrack.core.joints import N_JOINTS, SWING
from efficienttrack.core.progress import ProgressDisplay
from efficienttrack.core.settings import canonical_preset, check_fields, setting
from efficienttrack.data.metrics import compute_metrics
from efficienttrack.data.records import EpisodeRecord
from efficienttrack.data.references import Reference
from efficienttrack.deploy.episodes import Sent, batches, rollout
from efficienttrack.deploy.guard import GuardedRuntime
from efficienttrack.deploy.runtime import Runtime
from efficienttrack.learn.policy import AdjustmentPolicy, load_policy
from efficienttrack.systems.protocol import BatchedSystem

AUTO = "auto"
"""``ILCSettings.lead``: identify the lead from trial 0 (:func:`identify_lead`)."""
MAX_LEAD = 30
"""Steps: the largest lead :func:`identify_lead` considers (1.5 s at 20 Hz)."""
METHOD = "ilc"
"""The method's name in ``curve.json`` and the study (an oracle: it sees the test references)."""


@dataclass(frozen=True)
class ILCSettings:
    """Settings of the ILC oracle: the same on every system, the lead identified per system (docs/ilc.md)."""

    gain: tuple[float, ...] = setting((0.35, 0.35, 0.35, 0.35), gt=0, length=N_JOINTS)
    """L, the learning gain per joint (boom, arm, bucket, swing): the share of the last trial's error added to the
    correction each trial; a single number is taken for all four joints."""
    lead: tuple[int, ...] | int | str = setting(AUTO, length=N_JOINTS)
    """δ ≥ 0 per joint, steps by which the closed loop's response lags behind the step after the reference is sent
    (its dead time and, at a cycle's frequencies, most of its phase lag): the correction of step t learns from the
    error at step t + 1 + δ; a single integer is taken for all four joints; ``"auto"``: identified from trial 0's
    records (:func:`identify_lead`)."""
    cutoff_hz: float | None = setting(1.5, gt=0)
    """Cut-off frequency of the zero-phase low-pass Q over time, Hz (below the Nyquist frequency 1 / (2 dt));
    None: no filter."""
    filter_order: int = setting(2, ge=1)
    """Order of the Butterworth low-pass Q (run forwards and backwards: twice the order, no phase lag)."""
    trials: int = setting(80, ge=1)
    """Learning trials after trial 0 (the PD controller alone); each runs every test reference once. Fewer when the
    budget ends first."""

    def __post_init__(self) -> None:
        """Spread a single gain or lead over the four joints, check the fields, then that the lead is auto or ≥ 0."""
        if isinstance(self.gain, int | float) and not isinstance(self.gain, bool):
            object.__setattr__(self, "gain", (self.gain,) * N_JOINTS)
        if isinstance(self.lead, int) and not isinstance(self.lead, bool):
            object.__setattr__(self, "lead", (self.lead,) * N_JOINTS)
        check_fields(self)
        if self.lead != AUTO and not (isinstance(self.lead, tuple) and min(self.lead) >= 0):
            raise EfficientTrackError(
                f"ILCSettings.lead must be {AUTO} or {N_JOINTS} integers ≥ 0 (boom, arm, bucket, swing), got {self.lead!r}"
            )


ILC_PRESETS: dict[str, ILCSettings] = {"cpu": ILCSettings(), "tiny": ILCSettings(trials=5)}
"""The oracle's presets: ``cpu`` (80 trials) and ``tiny`` (5 trials, for tests)."""


def ilc_settings(preset: str | ILCSettings = "cpu") -> ILCSettings:
    """The ILC settings by preset name, or ``preset`` itself when it is an :class:`ILCSettings`.

    Args:
        preset: ``"cpu"``, ``"tiny"`` or an :class:`ILCSettings`.

    Returns:
        The settings.
    """
    if isinstance(preset, ILCSettings):
        return preset
    if isinstance(preset, str):
        preset = canonical_preset(preset)
    if not isinstance(preset, str) or preset not in ILC_PRESETS:
        raise EfficientTrackError(f"preset {preset!r}: unknown for ilc (known: {', '.join(ILC_PRESETS)}, or ILCSettings)")
    return ILC_PRESETS[preset]


def identify_lead(records: Sequence[EpisodeRecord], max_lead: int = MAX_LEAD) -> tuple[int, ...]:
    """δ per joint from runs of the closed loop: the delay at which the measured motion best follows the desired one.

    For each joint, the d ∈ [1, max_lead + 1] at which the desired velocity q*(t+2) − q*(t+1) and the measured one
    d steps later, q(t+d+1) − q(t+d), pooled over t and the records, have the largest cosine (1 for a pure delay,
    whatever the number of terms). A machine that reaches q*(s) at s + δ gives d = δ + 1. It reads the runs' motion,
    not their error; a joint that did not move gets 0.

    Args:
        records: runs of the closed loop (trial 0: the PD controller alone), each with ``q`` and ``q_des`` (T, 4) rad.
        max_lead: the largest δ considered, steps.

    Returns:
        (4,) δ per joint (boom, arm, bucket, swing), steps ≥ 0.
    """
    velocities = [_velocities(record) for record in records]
    cosine = np.zeros((max_lead + 1, N_JOINTS))
    for delta in range(max_lead + 1):
        d = delta + 1
        pairs = [(v[: len(v) - d], m[d:]) for v, m in velocities if len(v) > d]
        if not pairs:
            break
        desired, measured = (np.concatenate(side) for side in zip(*pairs, strict=True))
        norm = np.sqrt((desired**2).sum(0) * (measured**2).sum(0))
        cosine[delta] = np.where(norm > 0, (desired * measured).sum(0) / np.where(norm > 0, norm, 1.0), 0.0)
    return tuple(int(delta) for delta in np.argmax(cosine, axis=0))


def _velocities(record: EpisodeRecord) -> tuple[np.ndarray, np.ndarray]:
    """(T − 1, 4) rad per step: the changes of ``q_des`` and of ``q`` of one record (the swing's wrapped)."""
    desired, measured = np.diff(record.q_des, axis=0), np.diff(record.q, axis=0)
    desired[:, SWING], measured[:, SWING] = wrap(desired[:, SWING]), wrap(measured[:, SWING])
    return desired, measured


def ilc_update(
    correction: np.ndarray, error: np.ndarray, settings: ILCSettings, max_adjust: np.ndarray, dt: float
) -> np.ndarray:
    """One ILC update of N references' corrections (time-major), the update law of the module docstring.

    Args:
        correction: (T, N, 4) rad, a_k: the correction added to the desired position sent at each step.
        error: (T, N, 4) rad, ``wrap(q*(t+1) − q_k(t+1))``, the error of each step's target in trial k (zero where
            unknown).
        settings: the gain, lead and filter.
        max_adjust: (4,) rad, the adjustment bound.
        dt: the control period, s.

    Returns:
        (T, N, 4) rad, a_{k+1}, within ±max_adjust.
    """
    if not isinstance(settings.lead, tuple):
        raise EfficientTrackError("ilc_update: the lead is not known yet (identify it first: identify_lead)")
    ahead = np.zeros_like(error)
    for joint, lead in enumerate(settings.lead):
        ahead[: max(len(error) - lead, 0), :, joint] = error[lead:, :, joint]
    learned = correction + np.asarray(settings.gain) * ahead
    if settings.cutoff_hz is not None:
        b, a = butter(settings.filter_order, check_cutoff(settings, dt))
        learned = filtfilt(b, a, learned, axis=0, padlen=min(3 * len(b), len(learned) - 1))
    return np.clip(learned, -max_adjust, max_adjust)


def check_cutoff(settings: ILCSettings, dt: float) -> float | None:
    """The filter's cut-off as a fraction of the Nyquist frequency, checked against the system's control period.

    Args:
        settings: the settings (their ``cutoff_hz``).
        dt: the control period, s.

    Returns:
        ``cutoff_hz / (1 / (2 dt))`` in (0, 1), or None when there is no filter.

    Raises:
        EfficientTrackError: a cut-off at or above the Nyquist frequency.
    """
    if settings.cutoff_hz is None:
        return None
    nyquist = 0.5 / dt
    if settings.cutoff_hz >= nyquist:
        raise EfficientTrackError(f"ilc.cutoff_hz: {settings.cutoff_hz} Hz must be below the Nyquist frequency {nyquist:g} Hz")
    return settings.cutoff_hz / nyquist


class _CorrectionDriver:
    """The driver of :func:`rollout` that sends the desired position plus the stored correction, and keeps the errors.

    With a runtime (a policy behind the guard) it adds the correction to the policy's adjustment, within the runtime's
    bound; the policy's history keeps the policy's own references (module docstring).
    """

    def __init__(self, system: BatchedSystem, correction: np.ndarray, runtime: GuardedRuntime | None = None) -> None:
        self._limits = system.limits
        self._correction = correction
        self._runtime = runtime
        self.target = np.zeros_like(correction)
        """(T, N, 4) rad, q*(t+1) of each step."""
        self.measured = np.zeros_like(correction)
        """(T, N, 4) rad, q(t) of each step."""
        self._t = 0

    def start(self, obs0: np.ndarray) -> None:
        self._t = 0
        if self._runtime is not None:
            self._runtime.start(obs0)

    def step(self, obs: np.ndarray, q_des_future: np.ndarray) -> Sent:
        t, q_next = self._t, q_des_future[:, 0]
        if self._runtime is None:
            q_ref = self._limits.clamp(q_next + self._correction[t])
            fallback = np.zeros(len(obs), dtype=bool)
        else:
            sent = self._runtime.step(obs, q_des_future)
            bound = self._runtime.max_adjust
            adjustment = np.clip(sent.adjustment + self._correction[t], -bound, bound)
            q_ref = self._limits.clamp(q_next + adjustment)
            fallback = sent.fallback
        self.target[t], self.measured[t] = q_next, obs[:, :N_JOINTS]
        self._t += 1
        return Sent(q_ref=q_ref, adjustment=q_ref - q_next, fallback=fallback)

    def error(self) -> np.ndarray:
        """(T, N, 4) rad, ``wrap(q*(t+1) − q(t+1))``; the last step's (after the last observation seen) is zero."""
        error = np.zeros_like(self.target)
        error[:-1] = wrap(self.target[:-1] - self.measured[1:])
        return error


def run_trial(
    system: BatchedSystem,
    refs: Sequence[Reference],
    correction: np.ndarray,
    policy: AdjustmentPolicy | None = None,
) -> tuple[list[EpisodeRecord], np.ndarray]:
    """Run every reference once with its correction, all together on the batched system (the closed loop).

    A shorter reference holds its last desired position while the longer ones finish (as
    :func:`efficienttrack.deploy.episodes.rollout` runs them); its errors there are kept too, its record is cut to its length.

    Args:
        system: the closed-loop system, checked and opened.
        refs: the N references (each ≥ 3 positions).
        correction: (T, N, 4) rad, the correction of each step, T = the longest reference's steps.
        policy: a trained adjustment policy the correction is added to (deployed through the guarded runtime with the
            system's limits), or None for the correction alone.

    Returns:
        One record per reference (meta ``name``, ``loop`` = closed) and the errors (T, N, 4) rad,
        ``wrap(q*(t+1) − q(t+1))`` (zero at the last step).
    """
    records: list[EpisodeRecord] = []
    error = np.zeros_like(correction)
    for part in batches(system, len(refs)):
        group = refs[part]
        steps = max(len(ref) for ref in group) - 1
        runtime = None if policy is None else Runtime(policy, limits=system.limits, dt=system.dt)
        driver = _CorrectionDriver(system, correction[:steps, part], runtime)
        horizon = 1 if runtime is None else runtime.future_length
        with runtime if runtime is not None else nullcontext():
            group_records = rollout(system, [ref.q for ref in group], driver, horizon)
        for record, ref in zip(group_records, group, strict=True):
            record.meta.update(name=ref.name, loop="closed")
        records += group_records
        error[:steps, part] = driver.error()
    return records, error


def trial_steps(test_refs: Sequence[Reference]) -> int:
    """Interaction steps one trial costs: every test reference once, ``Σ (L_i − 1)``.

    Args:
        test_refs: the test references.

    Returns:
        The steps.
    """
    return sum(ref.steps for ref in test_refs)


def train_ilc(
    run: TrainingRun,
    preset: str | ILCSettings = "cpu",
    progress: ProgressDisplay | None = None,
    policy: str | Path | None = None,
) -> list[dict[str, Any]]:
    """The ORACLE: iterative learning control on the test references themselves, trial after trial (not a fair method).

    Trial 0 runs every test reference with no correction (the PD controller alone, or the policy alone when there is
    one: the module docstring's "on top of a policy"); each later trial runs them all
    again with the corrections learned from the trial before (:func:`ilc_update`), all references together on the
    batched system. A trial's own run is its measurement: the point of trial k has ``interaction_steps = k ·`` the
    steps of one trial (:func:`trial_steps`; the trials it learned from) and the metrics of its records. Trials run
    while ``k ≤ settings.trials`` and ``k · trial_steps ≤ budget``. ``folder/curve.json`` (``{"method": "ilc",
    "oracle": true, "loop", "seed", "budget", "system", "settings", "policy", "curve": [point, ...]}``) is rewritten atomically
    after each point. Deterministic: the same inputs give the same curve (wall times aside).

    Args:
        run: the run (:func:`~efficienttrack.baselines.curve.training_run`): ``loop`` ``"closed"`` only (the ILC
            corrects the reference sent to the position controller); ``test_refs``, the references the oracle learns
            on and is measured on; ``train_refs`` unused (the oracle learns on the test references; the run is the same
            as the other methods'); ``budget`` at least one trial's steps; ``seed`` unused (ILC is deterministic),
            written to the curve's header; ``folder`` gets ``curve.json`` (created; other files in it are left alone);
            ``eval_at``: each count recorded at the first trial whose count reaches it, besides trial 0; None: every
            trial. No ``validation_refs``: the corrections belong to the test references, so there is no policy to
            measure on others.
        preset: ``"cpu"``, ``"tiny"`` (:data:`ILC_PRESETS`) or an :class:`ILCSettings`.
        progress: a display to show the interaction count and the last MAE on, or None for no progress.
        policy: a policy checkpoint (``policy.pt``, its JSON next to it) whose adjustments the corrections are added
            to, deployed through the guarded runtime; None: the corrections alone.

    Returns:
        One point per recorded trial, trial 0 first: ``{"interaction_steps": int, "wall_seconds": float (time of the
        trials and updates before this trial; scoring excluded), "metrics": dict (compute_metrics of this trial)}``.

    Raises:
        EfficientTrackError: a run that is no TrainingRun, in the open loop or with validation references, an unknown
            preset, a budget smaller than one trial, a cut-off at or above the Nyquist frequency, a test reference
            outside the system's limits, an output folder being written by another process, a policy file that is
            missing or no adjustment policy (:func:`~efficienttrack.learn.policy.load_policy`'s message).
    """
    run = check_training_run(run)
    if run.loop == "open":
        raise EfficientTrackError("loop 'open': the ILC oracle has the closed loop only (it corrects the PD reference)")
    if run.validation_refs:
        raise EfficientTrackError(
            "validation_refs: the ILC oracle learns its corrections on the test references and has no policy to "
            "validate on others; give it a run without validation references"
        )
    settings = ilc_settings(preset)
    auto_lead = settings.lead == AUTO
    test_refs, budget, folder = run.test_refs, run.budget, run.folder
    per_trial = trial_steps(test_refs)
    if budget < per_trial:
        raise EfficientTrackError(f"budget {budget}: less than one ILC trial over the test references ({per_trial} steps)")
    trials = min(settings.trials, budget // per_trial)
    record_at = _recorded_trials(run.eval_at, per_trial, trials)
    header = {
        "method": METHOD,
        "oracle": True,
        "loop": run.loop,
        "seed": run.seed,
        "budget": budget,
        "system": run.system.to_dict(),
        "settings": asdict(settings),
        "policy": None if policy is None else str(policy),
    }
    adjustments = None if policy is None else load_policy(policy)
    with output_lock(folder / CURVE_FILE, "folder", folder=False):
        opened = run.system.open()
        check_cutoff(settings, opened.dt)
        for ref in test_refs:
            opened.limits.check_reference(ref.q, ref.name)
        recorder = CurveRecorder(run, header, opened, progress, trials * per_trial)
        max_adjust = np.asarray(opened.limits.max_adjust, dtype=np.float64)
        correction = np.zeros((max(len(ref) for ref in test_refs) - 1, len(test_refs), N_JOINTS))
        scoring = 0.0
        try:
            for k in range(trials + 1):
                wall = time.perf_counter() - recorder.start - scoring
                records, error = run_trial(opened, test_refs, correction, adjustments)
                if k == 0 and auto_lead:
                    lead = identify_lead(records)
                    settings = replace(settings, lead=lead)
                    recorder.header["lead_identified"] = list(lead)
                if k in record_at:
                    began = time.perf_counter()
                    recorder.add(k * per_trial, wall, compute_metrics(records), {"gradient_samples": 0})
                    scoring += time.perf_counter() - began
                recorder.show(k * per_trial)
                if k < trials:
                    correction = ilc_update(correction, error, settings, max_adjust, opened.dt)
        finally:
            recorder.close()
    return recorder.curve


def _recorded_trials(eval_at: Sequence[int] | None, per_trial: int, trials: int) -> set[int]:
    """The trials whose points are recorded: trial 0 and, per (checked) point, the first trial whose count reaches it."""
    if eval_at is None:
        return set(range(trials + 1))
    return {0} | {min(-(-p // per_trial), trials) for p in eval_at}

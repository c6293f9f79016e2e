"""Algorithm 1, data collection: the PD loop tracks the references with (or without) noise.

For every reference q*_{0:L−1}, the machine is reset to q*_0 and at each step t the reference
``q^r_{t+1} = q*_{t+1} + d_t`` is sent, with ``d_t = clip(n_t, −σ, σ)``, ``n_t ~ N(0, σ²)`` per joint, AR(1) in time
with ``noise_rho`` (0: white, the paper's), and ``σ ~ U(0, σ_max)`` drawn once per episode. The defaults (σ_max 0.1,
ρ 0.9) are slower and larger than the paper's (0.05, white; the ``paper`` preset keeps them): at ten passes they
tracked better on three plants (docs/comparison.md). The noise is an adjustment
of the reference like the policy's, so it passes the same limits: ``σ_max`` may not exceed the machine's adjustment
bound (refused before anything moves), and a noisy reference beyond the joint limits is clamped into them (the step's
guard bit ``CLAMPED``, counted in the record's ``meta["guard"]``). A pass runs every reference once. Each episode is
either noisy or clean (d = 0), and the noisy:clean mix follows ``noise_ratio`` (the paper's best is 9:2) over the
episodes, so that any number of passes keeps it: a single pass over 40 references gives 33 noisy and 7 clean episodes
(the paper's fastset). Interaction steps (I.S.) are the steps the machine was driven.

Every episode is flushed to ``out/.pass_<k>.partial/`` as soon as it (or its batch) has run, and
the folder becomes ``out/pass_<k>/`` when the pass is complete: an interrupted collection resumes
with the first episode not yet recorded. The noise of pass k, reference i, comes from its own
seeded generator, so a resumed or re-batched collection is identical to an uninterrupted one.

A real machine (a :class:`~efficienttrack.deploy.loop.Machine` adapter, the one ``deploy`` drives) is collected on through
the same fixed-rate loop as a deployed policy (:class:`LoopMachine`, :func:`run_pass_through_loop`): deadlines,
watchdogs, a = 0 at the first tick and ramped back to 0 at the end, the noise's change per tick limited to the
machine's ``max_adjust_rate``, one tick log per episode (``out/logs/pass_<k>/<reference>.jsonl``) made into its
record as ``deploy`` does. A simulator runs the same path on a simulated clock, as fast as it computes.
"""

from __future__ import annotations

import functools
import json
import os
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass
from functools import partial
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from efficienttrack.core.angles import wrap
from efficienttrack.core.configfile import MAX_SEED
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.joints import JOINT_NAMES
from efficienttrack.core.progress import ProgressDisplay
from efficienttrack.core.provenance import claim_folder
from efficienttrack.core.settings import check_fields, plain_form, setting
from efficienttrack.data.records import EpisodeRecord, load_records, save_records
from efficienttrack.data.references import Reference
from efficienttrack.deploy.deployment import records_from_log, run_episode
from efficienttrack.deploy.episodes import Guard, Sent, batches, rollout
from efficienttrack.deploy.loop import Loop, LoopConfig, LoopResult, TickLog, set_aside
from efficienttrack.deploy.machine import Clock, Machine
from efficienttrack.systems.limits import GuardLimits
from efficienttrack.systems.protocol import BatchedSystem

MAX_PASSES = 1000
"""Most passes over the references a collection may ask for (the paper: 10)."""
MAX_NOISE_RHO = 0.99
"""Largest correlation of the collection noise: at 1 it would never change within an episode."""
NOISE_MIX = "episode"
"""How ``collect.json`` names the noise mixing (noisy or clean per episode); folders mixed per pass are refused."""


@dataclass(frozen=True)
class CollectConfig:
    """Settings of Algorithm 1."""

    sigma_max: float = setting(0.1, ge=0)
    """Upper bound σ_max of the per-episode noise level σ ~ U(0, σ_max), rad (the paper's: 0.05; 0.1 since 2026-11-29)."""
    noise_ratio: tuple[float, float] = setting((9.0, 2.0), ge=0, length=2)
    """Noisy episodes : clean episodes, as relative weights (the paper's best mix is 9:2)."""
    noise_rho: float = setting(0.9, ge=0, le=MAX_NOISE_RHO, before=0.0)
    """ρ: correlation of consecutive steps of n_t, AR(1) with stationary std σ (0: the paper's white noise; 0.9 since
    2026-11-29, and folders made before read back as 0). A hydraulic joint follows slow noise and averages white noise
    out, so correlated noise moves it further off the reference at the same σ."""
    passes: int = setting(10, ge=1, le=MAX_PASSES)
    """Passes over the reference set (the paper: 10 passes over 40 references = 176,720 steps)."""
    seed: int = setting(0, ge=0, le=MAX_SEED)
    """Seed of the noise generators (in a run: the run's seed, :class:`~efficienttrack.workflow.config.RunConfig`)."""

    def __post_init__(self) -> None:
        """Check the fields (:func:`~efficienttrack.core.settings.check_fields`) and that the mix has a weight > 0."""
        check_fields(self)
        if sum(self.noise_ratio) == 0:
            raise EfficientTrackError(f"CollectConfig.noise_ratio: needs a weight > 0, got {self.noise_ratio}")

    @staticmethod
    def parse_noise_ratio(text: str, option: str = "--noise-ratio") -> tuple[float, float]:
        """Read a ``noise_ratio`` written as ``noisy:clean`` (the paper's notation, e.g. ``9:2``).

        Args:
            text: the two weights separated by a colon.
            option: where ``text`` came from, named in errors.

        Returns:
            (noisy, clean) weights; :class:`CollectConfig` checks their values.

        Raises:
            EfficientTrackError: not two numbers separated by a colon.
        """
        parts = text.split(":")
        try:
            noisy, clean = (float(part) for part in parts)
        except ValueError as exc:
            raise EfficientTrackError(f"{option} '{text}': expected noisy:clean, two numbers like 9:2") from exc
        return noisy, clean

    def to_dict(self) -> dict[str, Any]:
        """JSON-serializable form (:func:`~efficienttrack.core.settings.plain_form`: ``noise_rho`` only when not 0)."""
        return plain_form(self)

    @property
    def noise_ratio_text(self) -> str:
        """``noise_ratio`` as ``noisy:clean`` (``9:2``), read back exactly by :meth:`parse_noise_ratio`."""
        return ":".join(str(float(w)).removesuffix(".0") for w in self.noise_ratio)

    def noisy_episodes(self, pass_index: int, references: int) -> np.ndarray:
        """Which episodes of pass k are noisy: the ratio spread evenly over all episodes, seeded choice within a pass.

        Pass k gets ``⌊(k+1)·n·s⌉ − ⌊k·n·s⌉`` noisy episodes (n references, s = noisy share), so every
        prefix of passes keeps the ratio; which references they are is a permutation seeded by (seed, pass).

        Args:
            pass_index: k, the pass.
            references: n, the references in a pass.

        Returns:
            (n,) bool, True where the episode of reference i is noisy.
        """
        noisy, clean = self.noise_ratio
        share = noisy / (noisy + clean)
        done = np.floor(np.array([pass_index, pass_index + 1]) * references * share + 0.5 + 1e-9)  # rounded half up
        count = int(done[1] - done[0])
        chosen = np.random.default_rng([self.seed, pass_index, references]).permutation(references)[:count]
        mask = np.zeros(references, dtype=bool)
        mask[chosen] = True
        return mask


def pass_counts(budget: int, steps_per_pass: int) -> list[int]:
    """The collection passes EfficientTrack is run with: 1, 2, 5, 10, 20, 50 … while their steps fit the budget.

    Args:
        budget: interaction steps allowed.
        steps_per_pass: interaction steps of one pass (Σ (L_i − 1) over the training references), ≥ 1.

    Returns:
        The pass counts p (≤ ``collect.MAX_PASSES``) with p · steps_per_pass ≤ budget, ascending; empty when not even
        one pass fits.
    """
    counts: list[int] = []
    scale = 1
    while True:
        for p in (scale, 2 * scale, 5 * scale):
            if p > MAX_PASSES or p * steps_per_pass > budget:
                return counts
            counts.append(p)
        scale *= 10


class CollectResult(NamedTuple):
    """Outcome of :func:`collect`.

    Attributes:
        records: every episode, pass by pass (meta: name, sigma, pass, noisy, guard).
        interaction_steps: total steps the machine was driven (I.S.), including resumed passes.
        resumed_passes: passes read back from disk instead of run.
    """

    records: list[EpisodeRecord]
    interaction_steps: int
    resumed_passes: int


class NoiseDriver:
    """Collection references ``q*_{t+1} + d_t`` for N episodes with fixed per-episode noise, clamped into the limits.

    A driver of :func:`~efficienttrack.deploy.episodes.rollout` and, for one machine (N = 1), a runtime of the
    fixed-rate loop (:class:`~efficienttrack.deploy.loop.LoopRuntime`).

    Args:
        noise: (T_max, N, 4) rad, the clipped noise d_t of every step (zeros for clean episodes).
        limits: the machine's joint limits; a noisy reference beyond them is clamped into them.
    """

    future_length = 1
    """F: the noise needs only ``q*_{t+1}``."""

    def __init__(self, noise: np.ndarray, limits: GuardLimits) -> None:
        self.noise = noise
        self.limits = limits
        self._t = 0

    def start(self, obs0: np.ndarray) -> None:
        """Begin the episodes.

        Args:
            obs0: (N, 8) [rad, rad/s], the start observations (not needed for noise).
        """
        self._t = 0

    def step(self, obs: np.ndarray, q_des_future: np.ndarray) -> Sent:
        """Reference for step t+1: ``q*_{t+1}`` plus this step's noise.

        Args:
            obs: (N, 8) [rad, rad/s], ``o_t`` (not needed for noise).
            q_des_future: (N, h, 4) rad, ``q*_{t+1} …``; only ``[:, 0]`` is used.

        Returns:
            The sent reference (N, 4) rad, ``q_ref − q*_{t+1}`` as adjustment, no fallbacks, ``CLAMPED`` where the
            reference was clamped into the joint limits.
        """
        q_des = q_des_future[:, 0]
        wanted = q_des + self.noise[self._t]
        self._t += 1
        q_ref = self.limits.clamp(wanted)
        clamped = np.any(q_ref != wanted, axis=1)
        guard = np.where(clamped, Guard.CLAMPED.value, 0).astype(np.uint16)
        return Sent(q_ref=q_ref, adjustment=wrap(q_ref - q_des), fallback=np.zeros(len(q_ref), dtype=bool), guard=guard)

    def stop(self) -> None:
        """End the episodes (nothing to release)."""


def episode_noise(cfg: CollectConfig, pass_index: int, ref_index: int, steps: int) -> tuple[float, np.ndarray]:
    """Noise level and noise of one noisy episode, from its own generator (seed, pass, reference).

    Args:
        cfg: collection settings (``sigma_max``, ``seed``).
        pass_index: k, the pass.
        ref_index: i, the reference's position in the reference set.
        steps: T, steps of the episode.

    Returns:
        σ in rad (U(0, σ_max)) and d (steps, 4) rad: n_t ~ N(0, σ²), AR(1) in time with ``noise_rho``
        (``n_t = ρ n_{t−1} + √(1 − ρ²) ε_t``, stationary from the first step), clipped to ±σ.
    """
    rng = np.random.default_rng([cfg.seed, pass_index, ref_index])
    sigma = float(rng.uniform(0.0, cfg.sigma_max))
    n = rng.normal(0.0, sigma, size=(steps, 4))
    if cfg.noise_rho > 0:
        n[1:] *= np.sqrt(1.0 - cfg.noise_rho**2)
        n = autoregress(n, cfg.noise_rho)
    return sigma, np.clip(n, -sigma, sigma)


def autoregress(e: np.ndarray, rho: float, block: int = 256) -> np.ndarray:
    """The AR(1) filter ``x_t = ρ x_{t−1} + e_t`` (``x_{−1} = 0``) along axis 0, in numpy alone.

    scipy's ``lfilter([1], [1, −ρ], e, axis=0)`` computes the same, but the core install that collects on a machine has
    no scipy. Each block of ``block`` steps is one product with the lower-triangular matrix of ρ^(i−j), plus the carry
    of the block before decaying as ρ^(i+1).

    Args:
        e: (T, ...) innovations.
        rho: the correlation, in [0, 1).
        block: steps per matrix product.

    Returns:
        (T, ...) x, float64.
    """
    lag = np.subtract.outer(np.arange(block), np.arange(block))
    weights = np.where(lag >= 0, rho ** np.maximum(lag, 0), 0.0)  # (block, block): ρ^(i−j) for j ≤ i
    decay = rho ** np.arange(1, block + 1)
    x = np.empty(e.shape, dtype=np.float64)
    carry = np.zeros(e.shape[1:])
    for start in range(0, len(e), block):
        chunk = slice(start, min(start + block, len(e)))
        m = chunk.stop - start
        x[chunk] = np.tensordot(weights[:m, :m], e[chunk], axes=1) + np.multiply.outer(decay[:m], carry)
        carry = x[chunk.stop - 1]
    return x


def run_pass(
    system: BatchedSystem,
    references: Sequence[Reference],
    cfg: CollectConfig,
    pass_index: int,
    progress: ProgressDisplay | None = None,
    finished: Mapping[str, EpisodeRecord] | None = None,
    on_done: Callable[[list[EpisodeRecord]], None] | None = None,
) -> list[EpisodeRecord]:
    """One pass of Algorithm 1 over all references (together when the system is batched).

    Args:
        system: the closed-loop system.
        references: the references (``.name``, ``.q`` (L_i, 4) rad).
        cfg: collection settings.
        pass_index: k, which decides the noisy episodes (``cfg.noisy_episodes``) and seeds the noise.
        progress: progress display for the steps, or None.
        finished: episodes of this pass already recorded, by reference name; they are not run again.
        on_done: called with the records of every group of episodes as soon as it has run (to flush them).

    Returns:
        One record per reference; meta = {name, sigma, pass, noisy, guard} (guard: {"clamped": steps} where a noisy
        reference was clamped into the joint limits, else empty); ``q_ref`` = sent, ``q_des`` = desired.
    """
    noisy = cfg.noisy_episodes(pass_index, len(references))
    finished = finished or {}
    todo = [i for i, ref in enumerate(references) if ref.name not in finished]
    new: dict[str, EpisodeRecord] = {}
    for part in batches(system, len(todo)):
        indices = todo[part]
        arrays = [references[i].q for i in indices]
        noise = np.zeros((max(len(q) for q in arrays) - 1, len(indices), 4))
        sigmas = np.zeros(len(indices))
        for j, i in enumerate(indices):  # per-episode generators keep batching and resuming reproducible
            if noisy[i]:
                sigmas[j], noise[: len(arrays[j]) - 1, j] = episode_noise(cfg, pass_index, i, len(arrays[j]) - 1)
        try:
            records = rollout(system, arrays, NoiseDriver(noise, system.limits), 1, progress, f"pass {pass_index + 1}")
        except EfficientTrackError:
            raise
        except Exception as exc:  # the machine failed mid-pass: the episodes flushed so far stay, a rerun resumes
            names = ", ".join(references[i].name for i in indices)
            raise EfficientTrackError(
                f"collect: pass {pass_index + 1} failed on episode(s) {names}: {type(exc).__name__}: {exc}"
            ) from exc
        for record, i, sigma in zip(records, indices, sigmas, strict=True):
            guard = record.meta.get("guard", {})  # the steps clamped into the joint limits
            record.meta = {"name": references[i].name, "sigma": float(sigma), "pass": pass_index, "noisy": bool(noisy[i])}
            record.meta["guard"] = guard
            new[references[i].name] = record
        if on_done is not None:
            on_done(records)
    return [finished.get(ref.name) or new[ref.name] for ref in references]


@dataclass(frozen=True)
class LoopMachine:
    """A machine that collection drives through the fixed-rate loop, as ``deploy`` does (``collect --machine``).

    Attributes:
        make: reference → a new adapter for its episode (:func:`~efficienttrack.deploy.deployment.machine_parts`).
        limits: the machine's limits.
        clock: the loop's clock (``MONOTONIC`` on a machine; a simulated one runs a simulator as fast as it computes).
        name: what ``collect.json`` calls the machine (the adapter's import path, or the simulator's name).
        loop: the loop's timing and watchdogs.
        between: when the machine is not at an episode's start: ``"approach"`` it slowly through the loop first, or
            ``"stop"`` (:data:`~efficienttrack.deploy.deployment.BETWEEN_EPISODES`).
    """

    make: Callable[[Reference], Machine]
    limits: GuardLimits
    clock: Clock
    name: str
    loop: LoopConfig = LoopConfig()
    between: str = "approach"


def run_pass_through_loop(
    machine: LoopMachine,
    references: Sequence[Reference],
    cfg: CollectConfig,
    pass_index: int,
    logs: Path,
    progress: ProgressDisplay | None = None,
    finished: Mapping[str, list[EpisodeRecord]] | None = None,
    on_done: Callable[[list[EpisodeRecord]], None] | None = None,
) -> list[EpisodeRecord]:
    """One pass of Algorithm 1 through the fixed-rate loop, one reference after the other, each with its tick log.

    The episode of reference i has the noise of :func:`run_pass` (the same seeded draws), sent as the loop sends a
    policy's adjustment: none at the first tick, its change per tick limited to ``max_adjust_rate``, ramped to 0 at the
    end, clamped into the joint limits. Its records are made from its log (:func:`records_from_log`: a reading that
    was missing or old splits the episode, ``<reference>-2`` …).

    Args:
        machine: the machine and its loop.
        references: the references (``.name``, ``.q`` (L_i, 4) rad).
        cfg: collection settings.
        pass_index: k, which decides the noisy episodes and seeds the noise.
        logs: the folder of this pass's tick logs (created); the log of an episode that a watchdog stopped is kept
            as ``<reference>.stopped-<n>.jsonl`` when the episode is run again.
        progress: progress display for the episodes, or None.
        finished: records of the episodes of this pass already recorded, by reference name; not run again.
        on_done: called with each episode's records as soon as it has run (to flush them).

    Returns:
        The records, episode by episode (meta: name, reference, sigma, pass, noisy, guard, loop_events; source
        ``collect``).

    Raises:
        EfficientTrackError: a watchdog stopped an episode (its reason; the episodes before it are kept, a rerun resumes
            with it), or its log gave no record.
        KeyboardInterrupt: Ctrl-C or a stop signal during an episode (the loop sent the raw reference and closed the
            machine first).
    """
    noisy = cfg.noisy_episodes(pass_index, len(references))
    finished = finished or {}
    logs.mkdir(parents=True, exist_ok=True)
    task = None if progress is None else progress.add_task(f"pass {pass_index + 1} (episodes)", total=len(references))
    records: list[EpisodeRecord] = []
    for i, ref in enumerate(references):
        if ref.name in finished:
            records += finished[ref.name]
        else:
            sigma, noise = episode_noise(cfg, pass_index, i, ref.steps) if noisy[i] else (0.0, np.zeros((ref.steps, 4)))
            log_path = logs / f"{ref.name}.jsonl"
            set_aside(log_path)

            run = partial(_loop_episode, machine, ref, noise, log_path)
            result = run_episode(ref, run, machine.between, machine.make, machine.limits, machine.loop, machine.clock, logs)
            if result.reason == "interrupted":
                raise KeyboardInterrupt(result.error)
            if result.stopped:
                raise EfficientTrackError(
                    f"collect: pass {pass_index + 1}, reference {ref.name}: the loop stopped it at tick {result.ticks} "
                    f"({result.reason}: {result.error}); the episodes recorded before it are kept and its log is "
                    f"{log_path}; rerun the same command to resume with {ref.name}"
                )
            episode = records_from_log(log_path, shadow=False)
            if not episode:
                raise EfficientTrackError(f"collect: {log_path}: no two usable ticks in a row, no record (see its events)")
            for record in episode:
                record.meta.update(source="collect", sigma=float(sigma), noisy=bool(noisy[i]))
                record.meta["pass"] = pass_index
            if on_done is not None:
                on_done(episode)
            records += episode
        if progress is not None and task is not None:
            progress.advance(task)
    return records


def _loop_episode(machine: LoopMachine, ref: Reference, noise: np.ndarray, log_path: Path) -> LoopResult:
    """One episode of collection through the loop: the reference with ``noise`` (T, 4) rad added, logged to ``log_path``."""
    with TickLog(log_path, machine.loop.fsync_every) as log:
        loop = Loop(
            NoiseDriver(noise[:, None], machine.limits), machine.make(ref), machine.limits, machine.loop, machine.clock, log
        )
        return loop.run(ref.q, ref.name)


def by_reference(records: Sequence[EpisodeRecord]) -> dict[str, list[EpisodeRecord]]:
    """Records grouped by the reference they tracked (``meta["reference"]``, else their name), in their order.

    Args:
        records: episodes of one pass (the loop's may be several per reference).
    """
    groups: dict[str, list[EpisodeRecord]] = {}
    for record in sorted(records, key=lambda r: r.meta.get("first_tick", 0)):
        groups.setdefault(str(record.meta.get("reference", record.meta["name"])), []).append(record)
    return groups


def check_noise_level(sigma_max: float, limits: GuardLimits) -> None:
    """Refuse a noise level the machine's adjustment bound cannot hold, naming the joint and the bound.

    The noise moves the reference away from the desired path as the policy's adjustment does; the machine's limits
    say how far that may go (``max_adjust``), so a larger ``σ_max`` would ask for noise the guard forbids.

    Args:
        sigma_max: rad, the upper bound of the per-episode noise level.
        limits: the machine's limits.
    """
    bound = np.asarray(limits.max_adjust, dtype=np.float64)
    if sigma_max > bound.min():
        joint = int(np.argmin(bound))
        raise EfficientTrackError(
            f"collect.sigma_max: {sigma_max:g} rad exceeds the machine's adjustment bound of {bound[joint]:g} rad "
            f"({JOINT_NAMES[joint]}; max_adjust {', '.join(f'{b:g}' for b in bound)} rad): the noise is an adjustment of "
            "the reference, and the guard allows no more; lower it (collect --sigma-max, or --set collect.sigma_max=... on "
            "the commands that train) or widen max_adjust with --limits"
        )


def _pass_dir(out: Path, k: int) -> Path:
    return out / f"pass_{k:03d}"


def _flush(records: list[EpisodeRecord], folder: Path) -> None:
    save_records(records, folder)


def collect(
    system: BatchedSystem | LoopMachine,
    references: Sequence[Reference],
    cfg: CollectConfig,
    out: str | Path | None = None,
    progress: bool = True,
) -> CollectResult:
    """Algorithm 1: ``cfg.passes`` passes over the references, written to ``out`` pass by pass.

    Args:
        system: the closed-loop system (``load_system``), run batched; or a machine driven through the fixed-rate loop
            (:class:`LoopMachine`), one episode after the other.
        references: the references (``.name``, ``.q`` (L_i, 4) rad of desired positions), unique names.
        cfg: collection settings.
        out: folder for the records (``pass_<k>/<name>.npz`` plus ``collect.json``, and ``logs/`` of a
            :class:`LoopMachine`); passes already there are read back instead of run. None keeps everything in memory
            (a :class:`LoopMachine` needs a folder for its logs).
        progress: show progress (bars on a terminal, plain lines otherwise).

    Returns:
        All records, the interaction steps (I.S.) and how many passes were resumed from disk.

    Raises:
        EfficientTrackError: a reference outside the system's joint limits (before anything moves), or ``out`` holds a
            collection made with other settings or references.
    """
    if not references:
        raise EfficientTrackError("collect: no references given")
    looped = isinstance(system, LoopMachine)
    if looped and out is None:
        raise EfficientTrackError("collect: a machine driven through the loop needs an output folder for its tick logs")
    check_noise_level(cfg.sigma_max, system.limits)
    for ref in references:
        system.limits.check_reference(ref.q, ref.name)
    if cfg.noise_ratio[0] > 0 and not any(cfg.noisy_episodes(k, len(references)).any() for k in range(cfg.passes)):
        warnings.warn(
            f"collect: {cfg.passes} pass(es) over {len(references)} reference(s) at noisy:clean "
            f"{cfg.noise_ratio_text} give no noisy episode; the model will see no noise (use more passes)",
            stacklevel=2,
        )
    names = [ref.name for ref in references]
    folder = Path(out) if out is not None else None
    if folder is not None:
        steps = [ref.steps for ref in references]
        manifest = {"config": cfg.to_dict(), "noise_mix": NOISE_MIX, "references": names, "steps": steps}
        if isinstance(system, LoopMachine):
            manifest["loop"] = dict(asdict(system.loop), machine=system.name)
        manifest = json.loads(json.dumps(manifest))  # tuples as lists, as read back
        claim_folder(folder / "collect.json", manifest, "this folder holds a collection with other settings or references")
    records: list[EpisodeRecord] = []
    resumed = 0
    with ProgressDisplay(progress) as bar:
        passes = bar.add_task("collecting (passes)", total=cfg.passes)
        for k in range(cfg.passes):
            if folder is not None and _pass_dir(folder, k).is_dir():
                records += _pass_records(_pass_dir(folder, k), names)
                resumed += 1
            elif folder is None:
                assert not isinstance(system, LoopMachine)  # refused above
                records += run_pass(system, references, cfg, k, bar)
            else:
                partial = _pass_dir(folder, k).with_name(f".{_pass_dir(folder, k).name}.partial")
                finished = by_reference(load_records(partial)) if partial.is_dir() else {}
                flush = functools.partial(_flush, folder=partial)
                if isinstance(system, LoopMachine):
                    logs = folder / "logs" / _pass_dir(folder, k).name
                    records += run_pass_through_loop(system, references, cfg, k, logs, bar, finished, flush)
                else:
                    done = {name: group[0] for name, group in finished.items()}
                    records += run_pass(system, references, cfg, k, bar, done, flush)
                os.replace(partial, _pass_dir(folder, k))
            bar.advance(passes)
    return CollectResult(records=records, interaction_steps=sum(len(r) for r in records), resumed_passes=resumed)


def _pass_records(folder: Path, names: Sequence[str]) -> list[EpisodeRecord]:
    """The records of a finished pass, reference by reference in the order of ``names`` (all of a reference's)."""
    groups = by_reference(load_records(folder))
    missing = [name for name in names if name not in groups]
    if missing:
        raise EfficientTrackError(
            f"{folder}: episode(s) {', '.join(missing[:5])} missing from a finished pass; delete the folder to redo it"
        )
    return [record for name in names for record in groups[name]]

"""Fit a run into a wall-clock budget (``--time-budget MINUTES``) by training fewer optimizer steps.

Almost all of a run's time is training, and a training step's cost depends on the machine (it varied by 30 %
between days on one 2-core machine) and on what else runs on it. So the run measures it: after the collection and
the PD evaluation it times short trainings of each network on the collected data (:func:`step_seconds`; their setup
cancels out), estimates what every round's trainings and the rest of the run will take, and scales round 1's
optimizer steps by a factor ≤ 1 (:func:`budget_scale`). Before round 1's policy training and before each later
round it plans again from the time left, with the step times corrected by how long the finished trainings really took
(:class:`TimeBudget`): a machine can run a short probe a third faster than the minutes of training after it. The
factors are kept as stages, so a resumed run trains the same steps. The budget is a target, not a guarantee: work that
starts beside the run after the last plan slows its steps.

A run that is killed and rerun (resumed) counts the wall time of all its invocations, not only the rerun's: the seconds
spent are kept in ``OUT/stages/time_budget_spent.json`` (:data:`SPENT`), written when an invocation starts, every
:data:`HEARTBEAT` s while it runs (from a thread, so that a process killed with SIGKILL loses at most that much) and
when it stops; a rerun reads them back and plans from the minutes less all of it. The time between the kill and the
rerun does not count (the machine was not the run's). Work that a kill splits, the collection, the PD evaluation or a
training resumed from its checkpoint, counts from its start in the first invocation to its end (:meth:`TimeBudget.begin`,
:meth:`TimeBudget.took`): the part before the kill, the restart and the steps trained again since the last checkpoint
included. A resumed training's ``seconds`` are its last invocation's part only; a plan corrected by those alone would
take the machine for faster than it is and give the next training too many steps.

Every plan, once made, is kept on resume: round 1's (:data:`STAGE`), round 1's policy's and each later round's. A
training resumes from a checkpoint made for the planned steps (a training state made for other steps is refused: a new
factor would stop the rerun with an error, or throw the trained part away), and the later plans correct the step times
by how long the trainings of the planned steps took. So what a kill costs is not taken from a plan already made but
from the time left, by the next plan; a kill during the last plan's training (round K's, or round 1's policy's in a
1-round run) has no plan after it and may end the run late by what it cost. A rerun that adds rounds to a finished run
counts its minutes afresh from its own start, as before.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import json
import math
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, NamedTuple, TypeVar

import torch

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import write_json
from efficienttrack.data.records import EpisodeRecord
from efficienttrack.learn import dynamics, policy
from efficienttrack.learn.training import EVALUATIONS, TrainingSchedule
from efficienttrack.workflow.config import RunConfig
from efficienttrack.workflow.stages import RunLog, Stages

ScheduleT = TypeVar("ScheduleT", bound=TrainingSchedule)
"""A training's config: a :class:`~efficienttrack.learn.training.TrainingSchedule` (the model's or the policy's)."""

PROBE_STEPS = (1, 4, 24)
"""Optimizer steps of the short trainings of each network: a warm-up (the process's first steps are slow), then two
timed ones with one held-out evaluation each; the step time is the difference of those two over their 20 steps."""
MIN_SCALE = 0.05
"""Smallest share of the configured steps worth training; a budget that leaves less is refused."""
RESERVE = 0.05
"""Share of the budget kept for what the estimate leaves out (model errors, saving, the report's plots): with 3 %, a
15-minute run beside two training jobs took 15.3 minutes."""
LAST_PLAN_MARGIN = 0.15
"""Extra share of its training time that the last plan keeps free (round K's, or round 1's policy's in a 1-round run):
nothing corrects it afterwards. On a 2-core machine a later round's trainings took 0.95–1.15 × what the plan before
them predicted (10 plans in five 15-minute runs; one ended 8 s over with :data:`RESERVE` alone)."""
STAGE = "time_budget"
"""The stage that keeps round 1's factor, ``OUT/stages/time_budget.json``; round 1's policy's is
``time_budget_policy``, round k's ``time_budget_round_<k>``."""
SPENT = "time_budget_spent"
"""The run's wall time so far, ``OUT/stages/time_budget_spent.json`` (not a stage: rewritten as the run goes):
``{"spent_seconds": the seconds of every invocation so far, "invocations", "finished": whether the last one finished
the run, "work": {name: {"began": spent seconds when it began, "invocation", "seconds": what it took, once known}}}``."""
HEARTBEAT = 2.0
"""Seconds between two writes of :data:`SPENT` while a run goes on: a killed run loses at most this much of its time."""


class StepTimes(NamedTuple):
    """What the trainings cost on this machine, and the training windows (for epoch schedules).

    Attributes:
        model: s per optimizer step of g_θ's training.
        policy: s per optimizer step of π_φ's training.
        windows: training windows of the collected data.
        model_evaluation: s per held-out evaluation during g_θ's training (:data:`~efficienttrack.learn.training.EVALUATIONS`
            of them a training, however many steps it has).
        policy_evaluation: the same for π_φ.
    """

    model: float
    policy: float
    windows: int
    model_evaluation: float = 0.0
    policy_evaluation: float = 0.0


def step_seconds(train: Callable[[ScheduleT], Any], cfg: ScheduleT) -> tuple[float, float, Any]:
    """Seconds per optimizer step and per held-out evaluation of a training, from short runs of it.

    After a warm-up, runs of :data:`PROBE_STEPS` steps with one evaluation each give the step time (their difference:
    setup and evaluation cancel), and the short run again with two evaluations gives the evaluation's.

    Args:
        train: runs the training with a schedule and returns its result (``seconds``, ``windows``, the network first).
        cfg: the training's config.

    Returns:
        The seconds per step (> 0), per evaluation (≥ 0), and the longest probe's result.
    """

    def probe(steps: int, every: int) -> Any:
        return train(dataclasses.replace(cfg, steps=steps, epochs=None, save_every=steps, eval_every=every))

    warm_up, short, long = PROBE_STEPS
    probe(warm_up, warm_up)
    first, last, twice = probe(short, short), probe(long, long), probe(short, short // 2)
    per_step = max((last.seconds - first.seconds) / (long - short), last.seconds / long / 10, 1e-6)
    return per_step, max(twice.seconds - first.seconds, 0.0), last


def measure_step_times(
    cfg: RunConfig, records: Sequence[EpisodeRecord], held_out: Sequence[EpisodeRecord], device: torch.device
) -> StepTimes:
    """Time both trainings of ``cfg`` on ``records``, with their held-out evaluations and logs (nothing is kept).

    Args:
        cfg: the run's config (sizes, batches, horizons).
        records: the collected episodes.
        held_out: the episodes the trainings evaluate on.
        device: the training device.

    Returns:
        The costs and the window count.
    """
    with tempfile.TemporaryDirectory() as folder:
        logs = (Path(folder) / str(i) for i in itertools.count())
        common: dict[str, Any] = {"device": device, "seed": cfg.seed, "progress": False, "held_out": held_out}
        model_s, model_eval, probe = step_seconds(
            lambda c: dynamics.train_model(c, records, log_dir=next(logs), **common), cfg.model
        )
        policy_s, policy_eval, _ = step_seconds(
            lambda c: policy.train_policy(c, probe.model, records, log_dir=next(logs), **common), cfg.policy
        )
    return StepTimes(model_s, policy_s, probe.windows, model_eval, policy_eval)


class RoundCost(NamedTuple):
    """Round 1's training seconds by the measured costs, unscaled: what scales with the steps, and what does not.

    Attributes:
        model: g_θ's optimizer steps.
        policy: π_φ's optimizer steps.
        model_evaluations: g_θ's held-out evaluations (a fixed number per training).
        policy_evaluations: π_φ's.
    """

    model: float
    policy: float
    model_evaluations: float
    policy_evaluations: float

    @property
    def steps(self) -> float:
        """Both trainings' optimizer steps, s."""
        return self.model + self.policy

    @property
    def evaluations(self) -> float:
        """Both trainings' evaluations, s."""
        return self.model_evaluations + self.policy_evaluations


def round_seconds(cfg: RunConfig, times: StepTimes) -> RoundCost:
    """Round 1's training seconds by ``times``.

    Args:
        cfg: the run's config (round 1's steps of both trainings).
        times: the costs measured.
    """
    return RoundCost(
        cfg.model.total_steps(times.windows) * times.model,
        cfg.policy.total_steps(times.windows) * times.policy,
        EVALUATIONS * times.model_evaluation,
        EVALUATIONS * times.policy_evaluation,
    )


def budget_scale(cfg: RunConfig, times: StepTimes, seconds_left: float, other_seconds: float) -> tuple[float, float]:
    """The factor on every training's steps that fits the rest of the run into ``seconds_left``.

    Args:
        cfg: the run's config: round 1's steps, ``rounds`` and ``warm_budget`` (a later round's share of them).
        times: the costs of the trainings.
        seconds_left: the budget's seconds not spent yet.
        other_seconds: what the rest of the run takes besides training (deployments, evaluations).

    Returns:
        The factor (≤ 1: the configured steps are the most trained) and the training seconds they would take unscaled.

    Raises:
        EfficientTrackError: the budget leaves less than :data:`MIN_SCALE` of the configured training.
    """
    cost = round_seconds(cfg, times)
    scalable, fixed = cost.steps * (1 + (cfg.rounds - 1) * cfg.warm_budget), cost.evaluations * cfg.rounds
    available = seconds_left * (1 - RESERVE) - other_seconds - fixed
    scale = min(1.0, available / scalable)
    if scale < MIN_SCALE:
        raise EfficientTrackError(
            f"--time-budget {cfg.time_budget:g} min: {max(available, 0) / 60:.1f} min would be left for training steps, "
            f"less than {MIN_SCALE:.0%} of the {scalable / 60:.1f} min they take on this machine; give more minutes or "
            "fewer steps"
        )
    return scale, scalable + fixed


class TimeBudget:
    """A run's budget: the factor on round 1's training steps, then on each later training's, re-planned as the run goes.

    Round 1's factor comes from probe step times (:func:`measure_step_times`). Before round 1's policy training and
    before each later round the plan is redone from the time left, with the step times corrected by how much longer the
    finished trainings really took than the probes predicted (saving, a machine slower than during the probes, other
    work on it). The last plan keeps :data:`LAST_PLAN_MARGIN` of its training free, as no later one can correct it.
    Each factor is kept as a stage (:data:`STAGE`, ``time_budget_policy``, ``time_budget_round_<k>``), so a
    resumed run trains the same steps. The time spent counts every invocation of the run: the earlier ones' seconds are
    read from :data:`SPENT`, which :meth:`counting` keeps up to date while this one runs.

    Args:
        cfg: the run's config, with ``time_budget`` set (minutes).
        stages: the run's finished-stage markers (:data:`SPENT` lies in their folder).
        log: where to say what was decided.
        started: ``time.perf_counter()`` when this invocation of the run began; its time counts from there, added to
            what the earlier invocations spent (none when the last one finished the run: a rerun that adds rounds).

    Raises:
        EfficientTrackError: the config has no budget, or :data:`SPENT` is unreadable.
    """

    def __init__(self, cfg: RunConfig, stages: Stages, log: RunLog, started: float) -> None:
        if cfg.time_budget is None:
            raise EfficientTrackError("TimeBudget: the config has no time_budget")
        self.cfg, self.stages, self.log, self.started = cfg, stages, log, started
        self.facts: dict[str, Any] = {}
        self.scales: list[float] = []
        self.policy_scale: float | None = None
        self.path = stages.folder / f"{SPENT}.json"
        spent, invocations, finished, self.work = read_spent(self.path)
        self.spent_before = 0.0 if finished else spent
        """Seconds the run's earlier invocations spent."""
        self.invocation = invocations + 1
        self.finished = False
        self._lock = threading.RLock()

    def seconds_spent(self) -> float:
        """Wall seconds the run has spent so far: its earlier invocations' and this one's."""
        return self.spent_before + (time.perf_counter() - self.started)

    @contextlib.contextmanager
    def counting(self) -> Iterator[None]:
        """Keep :data:`SPENT` up to date while the block runs: at its start, every :data:`HEARTBEAT` s and at its end.

        A thread writes it, so that a killed process (SIGKILL, or SIGTERM at its default action: no ``finally`` runs)
        loses at most :data:`HEARTBEAT` s; an interrupt (Ctrl-C) or an error writes it once more on the way out.
        """
        stop = threading.Event()

        def beat() -> None:
            while not stop.wait(HEARTBEAT):
                with contextlib.suppress(OSError, EfficientTrackError):  # the next write in the run's thread reports it
                    self._save()

        self._save()
        thread = threading.Thread(target=beat, name="efficienttrack-time-budget", daemon=True)
        thread.start()
        try:
            yield
        except BaseException:
            stop.set()
            thread.join()
            with contextlib.suppress(OSError, EfficientTrackError):  # the error on its way out is the one to show
                self._save()
            raise
        stop.set()
        thread.join()
        self._save()

    def begin(self, name: str) -> None:
        """Note that work ``name`` (the collection, an evaluation, a training) begins now, unless an earlier invocation did.

        Args:
            name: the work, e.g. ``"collect"``, ``"evaluate_pd"``, ``"round_<k>_model"``.
        """
        with self._lock:
            if name not in self.work:
                self.work[name] = {"began": self.seconds_spent(), "invocation": self.invocation}
                self._save()

    def took(self, name: str, seconds: float) -> float:
        """What work ``name`` took: ``seconds`` when it ran within this invocation, else the run's time from its start.

        Work that a kill split (begun in an earlier invocation, finished in this one) took the part before the kill,
        the restart and what was done again, which ``seconds`` (this invocation's part, as a resumed training reports)
        leaves out; the run's time since :meth:`begin` counts them all. The answer is kept, so a later call (a rerun)
        gets the same.

        Args:
            name: the work, as given to :meth:`begin`.
            seconds: what this invocation measured of it (its whole time when it was not split).

        Returns:
            The seconds it took (``seconds`` for work never begun with :meth:`begin`, e.g. in a folder older than it).
        """
        with self._lock:
            entry = self.work.get(name)
            if entry is None:
                return seconds
            if "seconds" not in entry:
                split = entry["invocation"] != self.invocation
                entry["seconds"] = max(seconds, self.seconds_spent() - entry["began"]) if split else seconds
                self._save()
            return float(entry["seconds"])

    def finish(self) -> None:
        """Note that the run is finished: a later invocation (adding rounds) counts its minutes from its own start."""
        with self._lock:
            self.finished = True
            self._save()

    def first_round(
        self,
        records: Sequence[EpisodeRecord],
        held_out: Sequence[EpisodeRecord],
        device: torch.device,
        pass_seconds: float,
        evaluation_seconds: float,
    ) -> RunConfig:
        """Round 1's config: its steps scaled so that every round fits (probes the step times on ``records``).

        Args:
            records: the collected episodes (the probes train on them).
            held_out: the episodes the trainings evaluate on.
            device: the training device.
            pass_seconds: what one collection pass took here (a later round deploys one pass).
            evaluation_seconds: what one evaluation on the test references took here.

        Returns:
            The config round 1 trains with.
        """
        cfg = self.cfg
        facts = self.stages.done(STAGE, ("scale", "times", "other_seconds"))
        if facts is None:
            self.log.print(f"time budget {cfg.time_budget:g} min: timing short trainings of both networks on this machine")
            times = measure_step_times(cfg, records, held_out, device)
            other = cfg.rounds * evaluation_seconds + (cfg.rounds - 1) * pass_seconds
            scale, training = budget_scale(cfg, times, self._seconds_left(), other)
            facts = self.stages.finish(
                STAGE,
                {"scale": scale, "times": times._asdict(), "unscaled_training_seconds": training, "other_seconds": other},
            )  # fmt: skip
            self.log.print(
                f"time budget {cfg.time_budget:g} min: {times.model * 1e3:.0f} ms per model step, {times.policy * 1e3:.0f} "
                f"ms per policy step; the configured training takes {training / 60:.1f} min, "
                + ("it fits" if scale >= 1 else f"so round 1 trains {scale:.0%} of its steps")
            )
        self.facts = facts
        self.scales = [facts["scale"]]
        return self._scaled(facts["scale"])

    def first_policy(self, model_seconds: float) -> RunConfig:
        """Round 1's config for π_φ's training: its steps scaled again, from how long g_θ's training really took.

        The probes time a few seconds of training; the round-1 trainings that follow take minutes, and a machine's
        speed can change in between. g_θ's training says how much, before the other half of round 1 begins.

        Args:
            model_seconds: what round 1's g_θ training took, s.

        Returns:
            The config whose ``policy`` round 1 trains (its ``model`` is round 1's, already trained).
        """
        cfg, name = self.cfg, f"{STAGE}_policy"
        facts = self.stages.done(name, ("scale",))
        if facts is None:
            cost = round_seconds(cfg, StepTimes(**self.facts["times"]))
            predicted = cost.model * self.scales[0] + cost.model_evaluations
            slower = model_seconds / predicted if predicted > 0 else 1.0
            later = cfg.rounds - 1
            other = self.facts["other_seconds"] + slower * (cost.policy_evaluations + later * cost.evaluations)
            training = slower * (cost.policy + later * cfg.warm_budget * cost.steps)
            facts = self._replan(name, slower, other, training, last=later == 0)
            share = "trains its full steps" if facts["scale"] >= 1 else f"trains {facts['scale']:.0%} of its steps"
            self.log.print(f"time budget: the model's training took {slower:.2f} × the estimate; round 1's policy {share}")
        self.policy_scale = facts["scale"]
        return self._scaled(facts["scale"])

    def later_round(self, k: int, trained_seconds: float) -> RunConfig:
        """Round k's config (k ≥ 2), its steps scaled so that rounds k … K fit into the time left.

        Args:
            k: the round.
            trained_seconds: what the trainings of rounds 1 … k − 1 really took, s.

        Returns:
            The config round k trains with (``run_round`` takes ``warm_budget`` of its steps).
        """
        cfg, name = self.cfg, f"{STAGE}_round_{k}"
        facts = self.stages.done(name, ("scale",))
        if facts is None:
            cost = round_seconds(cfg, StepTimes(**self.facts["times"]))  # round 1 unscaled, by the probes
            first_policy = self.scales[0] if self.policy_scale is None else self.policy_scale
            predicted = (
                cost.model * self.scales[0]
                + cost.policy * first_policy
                + cost.steps * sum(self.scales[1:]) * cfg.warm_budget
                + cost.evaluations * len(self.scales)
            )
            slower = trained_seconds / predicted if predicted > 0 else 1.0
            rest = cfg.rounds - k + 1
            other = self.facts["other_seconds"] * rest / cfg.rounds + rest * cost.evaluations * slower
            facts = self._replan(name, slower, other, rest * cfg.warm_budget * cost.steps * slower, last=k == cfg.rounds)
            share = "its full steps" if facts["scale"] >= 1 else f"{facts['scale']:.0%} of its steps"
            self.log.print(f"time budget: the trainings so far took {slower:.2f} × the estimate; round {k} trains {share}")
            if facts["scale"] <= MIN_SCALE:
                self.log.print(f"time budget: spent; round {k} trains the fewest steps allowed ({MIN_SCALE:.0%})")
        self.scales.append(facts["scale"])
        return self._scaled(facts["scale"])

    def summary(self) -> dict[str, Any]:
        """What was planned, for ``metrics.json``.

        Returns:
            ``{"minutes", "scales": one factor per round so far (round 1's: its model's), "round_1_policy_scale",
            "times": the costs measured (:class:`StepTimes`), "seconds_spent": the run's wall seconds so far, every
            invocation's (:meth:`seconds_spent`)}``.
        """
        return {
            "minutes": self.cfg.time_budget,
            "scales": self.scales,
            "round_1_policy_scale": self.policy_scale,
            "times": self.facts.get("times"),
            "seconds_spent": round(self.seconds_spent(), 2),
        }

    def _replan(self, name: str, slower: float, other: float, training: float, last: bool) -> dict[str, Any]:
        """Finish stage ``name`` with the factor that fits ``training`` s and ``other`` s into the time left.

        ``training`` is what the optimizer steps still to train take unscaled, at the corrected step times; the last
        plan keeps :data:`LAST_PLAN_MARGIN` of it free besides the reserve.
        """
        available = self._seconds_left() * (1 - RESERVE) - other
        needed = training * (1 + LAST_PLAN_MARGIN) if last else training
        scale = min(1.0, max(available / needed, MIN_SCALE))
        return self.stages.finish(name, {"scale": scale, "slower_than_probed": slower, "seconds_for_training": available})

    def _seconds_left(self) -> float:
        assert self.cfg.time_budget is not None  # checked in __init__
        return self.cfg.time_budget * 60 - self.seconds_spent()

    def _save(self) -> None:
        """Write :data:`SPENT` (from the run's thread or :meth:`counting`'s)."""
        with self._lock:
            write_json(
                self.path,
                {
                    "spent_seconds": self.seconds_spent(),
                    "invocations": self.invocation,
                    "finished": self.finished,
                    "work": self.work,
                },
            )

    def _scaled(self, scale: float) -> RunConfig:
        if scale >= 1:
            return self.cfg
        return dataclasses.replace(self.cfg, model=self.cfg.model.scaled(scale), policy=self.cfg.policy.scaled(scale))


def read_spent(path: Path) -> tuple[float, int, bool, dict[str, dict[str, Any]]]:
    """The run's time so far, as :data:`SPENT` keeps it; nothing spent when the file does not exist.

    Args:
        path: ``OUT/stages/time_budget_spent.json``.

    Returns:
        The seconds spent, the invocations, whether the last one finished the run, and the work noted
        (:meth:`TimeBudget.begin`).

    Raises:
        EfficientTrackError: the file is unreadable or malformed, naming it and the fix.
    """
    if not path.exists():
        return 0.0, 0, False, {}
    try:
        data = json.loads(path.read_text())
        spent, invocations, finished = float(data["spent_seconds"]), data["invocations"], data["finished"]
        work = {str(name): dict(entry) for name, entry in data["work"].items()}
        if not math.isfinite(spent) or spent < 0 or not isinstance(invocations, int) or not isinstance(finished, bool):
            raise ValueError("bad spent_seconds, invocations or finished")
        for entry in work.values():
            if not math.isfinite(float(entry["began"])) or not isinstance(entry["invocation"], int):
                raise ValueError("bad work entry")
    except (OSError, ValueError, TypeError, KeyError, AttributeError) as exc:
        raise EfficientTrackError(
            f"{path}: the time budget's record of the run's time is unreadable ({exc}); delete it to count from the next "
            "invocation only, or start afresh with --force"
        ) from exc
    return spent, invocations, finished, work

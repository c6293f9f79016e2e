"""Fit a run into a wall-clock budget (``--time-budget MINUTES``) by training fewer optimizer steps, or more.

Almost all of a run's time is training, and a training step's cost depends on the machine (it varied by 30 % between
days on one 2-core machine) and on what else runs on it. So the run measures it: after the collection and the PD
evaluation it times short trainings of each network (:func:`measure_step_times`). Before every training,
:class:`Planner` scales its steps by the factor ≤ 1 that fits it, every training after it and the deployments and
evaluations left into the time left (:func:`fit`), at the step times corrected by how long the finished trainings took
against the prediction (a short probe can run a third faster than the minutes of training after it), each network's by
its own trainings once it has trained: in three 15-minute runs the policy's took 1.10–1.31 × their probe, the model's
0.88–1.15 ×. Minutes to spare go to the models' trainings first, up to :data:`MAX_MODEL_SCALE` × their steps, as long
as the policies keep room for theirs (:data:`KEPT_FOR_POLICIES`), then to the policies', up to :data:`MAX_POLICY_SCALE`
× theirs. The time spent and what each stage took come from the run's
:class:`~efficienttrack.workflow.ledger.Ledger`, so a killed and rerun run plans from what is actually left. Each
factor is kept as a stage: a resumed training trains the steps its checkpoint was made for. The budget is a target, not
a guarantee: work that starts beside the run after the last plan slows its steps.
"""

from __future__ import annotations

import dataclasses
import itertools
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple, TypeVar

import torch

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.data.records import EpisodeRecord
from efficienttrack.learn import dynamics, policy
from efficienttrack.learn.settings import TrainingSchedule
from efficienttrack.learn.training import EVALUATIONS
from efficienttrack.workflow.config import RunConfig
from efficienttrack.workflow.ledger import Ledger
from efficienttrack.workflow.stages import COLLECT, PARTS, PROBE, RunLog, evaluation, plan

ScheduleT = TypeVar("ScheduleT", bound=TrainingSchedule)
"""A training's config: a :class:`~efficienttrack.learn.settings.TrainingSchedule` (the model's or the policy's)."""

PROBE_STEPS = (1, 4, 24)
"""Optimizer steps of the short trainings of each network: a warm-up (the process's first steps are slow), then two
timed ones with one held-out evaluation each; the step time is the difference of those two over their 20 steps."""
MIN_SCALE = 0.05
"""Smallest share of the configured steps worth training; a budget that leaves less before the first training is
refused, and a later plan trains at least this share."""
RESERVE = 0.05
"""Share of the budget kept for what the estimate leaves out (model errors, saving, the report's plots): with 3 %, a
15-minute run beside two training jobs took 15.3 minutes."""
MAX_MODEL_SCALE = 3.0
"""Most share of its configured steps a model's training takes when the budget leaves room. With the policy's gradient
capped (``policy.row_cap``), three times the model's 4,000 steps gave a policy a fifth to a quarter better on the
validation references of the paper's simulator and its variant with a delay, a lag and a dead band, and as good on the
xe75 (docs/comparison.md, "Exploding gradients"); ten times was better still on one seed of the paper's simulator, worse
on the other. Through a 20-minute budget, three times the model's steps beat 1.5 times the policy's by 21–39 % on the
validation references of those two plants and was level on the xe75 (−2 % and +1 %; 2 seeds each, docs/rounds.md). Not
tuned beyond those points, and measured at the model's rate before 2026-12-07 (1e-3): with today's faster rate the
preset's steps are closer to converged, and three times them may buy less; not remeasured."""
MAX_POLICY_SCALE = 1.5
"""Most share of its configured steps a policy's training takes when the budget leaves room after the models. 2.7–2.8
times the policy's 1,500 steps of before 2026-11-29, with 20 minutes, tracked 5 % better on the validation references
of the xe75 and the paper's simulator (docs/rounds.md). Not tuned: 4,500 steps, 1.5 times today's 3,000, is the most
measured."""
KEPT_FOR_POLICIES = 1.5
"""Times their predicted seconds that the policies' trainings are kept when the models take minutes to spare. A
policy's trainings took 1.10–1.31 × their probe and the last plan keeps :data:`LAST_PLAN_MARGIN` free, so with 1.5 the
policies still train their configured steps after a model that ran slower than planned; what they do not need is
theirs at their own plans."""
LAST_PLAN_MARGIN = 0.15
"""Extra share of its time that the last training's plan keeps free: nothing corrects it afterwards. On a 2-core
machine a later round's trainings took 0.95–1.15 × what the plan before them predicted (10 plans in five 15-minute
runs; one ended 8 s over with :data:`RESERVE` alone)."""


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


def fit(seconds_left: float, other: float, trainings: Sequence[tuple[float, float]], last: bool) -> float:
    """The factor on the steps of ``trainings`` that fits them and ``other`` seconds into ``seconds_left``.

    Args:
        seconds_left: the budget's seconds not spent yet.
        other: what the rest of the run takes besides training (deployments, test evaluations), s.
        trainings: (seconds its steps take unscaled, seconds of its held-out evaluations) of this training and every
            one after it, at the corrected step times.
        last: this is the run's last training: :data:`LAST_PLAN_MARGIN` of its time is kept free.

    Returns:
        The factor; above 1 when everything fits with room to spare (the caller caps it).
    """
    scalable, fixed = sum(t[0] for t in trainings), sum(t[1] for t in trainings)
    available = seconds_left * (1 - RESERVE) - other - fixed
    return available / (scalable * (1 + LAST_PLAN_MARGIN) if last else scalable)


class Planner:
    """The factor on each training's steps: 1 without a budget; with one, what fits the rest of the run into it.

    A tight budget scales every training left by one factor below 1. When everything fits at the configured steps,
    the models share the rest up to :data:`MAX_MODEL_SCALE`, the policies' time kept (:data:`KEPT_FOR_POLICIES`), and
    the policies share what the models leave, up to :data:`MAX_POLICY_SCALE`.

    Args:
        cfg: the run's config (``time_budget`` minutes, or None).
        ledger: the run's ledger: the time spent, what each stage took, and where the plans are kept.
        log: where to say what was decided.
        probe: measures the step times (:func:`measure_step_times` on the collected data), once per run.
    """

    def __init__(self, cfg: RunConfig, ledger: Ledger, log: RunLog, probe: Callable[[], StepTimes]) -> None:
        self.cfg, self.ledger, self.log, self.probe = cfg, ledger, log, probe
        self.scales: dict[str, float] = {}

    def scale(self, k: int, part: str) -> float:
        """The factor on round k's training ``part`` (``model`` or ``policy``), planned once and kept as a stage."""
        if self.cfg.time_budget is None:
            return 1.0
        times = StepTimes(**self.ledger.once(PROBE, self._probe, keys=("times",))["times"])
        facts = self.ledger.once(plan(part), lambda: self._plan(k, part, times), k, ("scale",))
        self.scales[self.ledger.key(part, k)] = facts["scale"]
        return facts["scale"]

    def summary(self) -> dict[str, Any] | None:
        """What was planned, for ``metrics.json``.

        Returns:
            None without a budget, else ``{"minutes", "scales": {training: factor}, "times": the step times measured
            (:class:`StepTimes`), "seconds_spent": every invocation's}``.
        """
        if self.cfg.time_budget is None:
            return None
        times = self.ledger.facts.get(PROBE, {}).get("times")
        return {"minutes": self.cfg.time_budget, "scales": self.scales, "times": times,
                "seconds_spent": round(self.ledger.seconds_spent(), 2)}  # fmt: skip

    def _probe(self) -> dict[str, Any]:
        self.log.print(f"time budget {self.cfg.time_budget:g} min: timing short trainings of both networks on this machine")
        times = self.probe()
        self.log.print(f"time budget: {times.model * 1e3:.0f} ms per model step, {times.policy * 1e3:.0f} ms per policy step")
        return {"times": times._asdict()}

    def _plan(self, k: int, part: str, times: StepTimes) -> dict[str, Any]:
        """Plan round k's ``part``: the trainings before it say how much slower than probed the machine is."""
        cfg, ledger = self.cfg, self.ledger
        order = list(itertools.product(range(1, cfg.rounds + 1), PARTS))
        now = order.index((k, part))

        def cost(j: int, name: str) -> tuple[float, float]:  # (steps, evaluations) of round j's training, unscaled
            schedule, step, evaluate = (
                (cfg.model, times.model, times.model_evaluation) if name == "model"
                else (cfg.policy, times.policy, times.policy_evaluation)
            )  # fmt: skip
            share = 1.0 if j == 1 else cfg.warm_budget
            return schedule.total_steps(times.windows) * step * share, EVALUATIONS * evaluate

        finished = [(name, cost(j, name), ledger.key(name, j)) for j, name in order[:now]]

        def took(names: Sequence[str]) -> float | None:  # trained / predicted seconds of the finished ``names``
            done = [(costs, key) for name, costs, key in finished if name in names]
            predicted = sum(steps * self.scales[key] + evaluations for (steps, evaluations), key in done)
            return sum(ledger.facts[key]["seconds"] for _, key in done) / predicted if done and predicted > 0 else None

        overall, slower = took(PARTS), {}
        for name in PARTS:  # each network's own ratio once it has trained, before it every training's
            own = took([name])
            slower[name] = own if own is not None else overall if overall is not None else 1.0
        pass_seconds = ledger.facts[COLLECT].get("seconds", 0.0) / cfg.collect.passes
        other = (cfg.rounds - k + 1) * ledger.facts[evaluation("pd")].get("seconds", 0.0) + (cfg.rounds - k) * pass_seconds
        rest = []
        for j, name in order[now:]:
            steps, evaluations = cost(j, name)
            rest.append((slower[name] * steps, slower[name] * evaluations))
        assert cfg.time_budget is not None  # scale() plans only with a budget
        left = cfg.time_budget * 60 - ledger.seconds_spent()
        last = now == len(order) - 1
        scale = fit(left, other, rest, last)
        if scale > 1:  # room to spare: the models take it first, then the policies what the models leave
            names = [name for _, name in order[now:]]
            models, policies = ([cost for cost, name in zip(rest, names, strict=True) if name == which] for which in PARTS)
            kept = KEPT_FOR_POLICIES * sum(map(sum, policies))  # the policies' room
            model_scale = min(MAX_MODEL_SCALE, max(1.0, fit(left, other + kept, models, last=False))) if models else 1.0
            if part == "policy":
                for_models = sum(model_scale * steps + evaluations for steps, evaluations in models)
                scale = fit(left, other + for_models, policies, last)
            else:
                scale = model_scale
        if not finished and scale < MIN_SCALE:
            training = sum(steps for steps, _ in rest)
            raise EfficientTrackError(
                f"--time-budget {cfg.time_budget:g} min: less than {MIN_SCALE:.0%} of the {training / 60:.1f} min the "
                "configured training steps take on this machine would fit; give more minutes or fewer steps"
            )
        scale = min(MAX_POLICY_SCALE if part == "policy" else MAX_MODEL_SCALE, max(scale, MIN_SCALE))
        if overall is None:
            slowness = ""
        elif took(["policy"]) is None:
            slowness = f"the trainings so far took {overall:.2f} × the estimate; "
        else:
            slowness = (
                f"the model's trainings took {slower['model']:.2f} ×, the policy's {slower['policy']:.2f} × the estimate; "
            )
        share = "its full steps" if scale == 1 else f"{scale:.0%} of its steps" if scale < 1 else f"{scale:.2f} × its steps"
        self.log.print(f"time budget: {slowness}round {k}'s {part} trains {share}")
        return {"scale": scale, "slower_than_probed": slower, "other_seconds": other, "seconds_left": left}

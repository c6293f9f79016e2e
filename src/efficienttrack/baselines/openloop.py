"""EfficientTrack in the open loop (the paper's "Ours (Open.)"): a model of the plant itself, a policy that sends PWM.

The same method as the closed loop (:func:`efficienttrack.workflow.pipeline.run_pipeline`), one level down:

1. **collect** (Algorithm 1, :func:`efficienttrack.workflow.collect.run_pass`): the PD controller drives the plant along the
   training references with noise on its reference (σ ~ U(0, σ_max) per episode, noisy:clean 9:2); the records keep
   the PWM u the PD law applied, so they are (o, u) sequences of the plant.
2. **model**: g_θ of the plant, ô_{t+1} = o_t + g_θ(o_H, u_H, u_t) (:class:`~efficienttrack.learn.dynamics.PlantModel`),
   trained by the closed loop's multi-step trainer (:func:`~efficienttrack.learn.dynamics.train_model`).
3. **policy**: u_t / 1000 = π_φ(o_H, u_H, q*_F) (:class:`~efficienttrack.learn.policy.PWMPolicy`, tanh-bounded to ±1000 PWM),
   trained through the frozen g_θ on the discounted tracking error plus k_smooth × the command's change
   (:func:`~efficienttrack.learn.policy.train_policy`). Where the closed loop's policy starts at a = 0, which is the PD
   controller, u = 0 is a machine standing still; so π_φ first imitates the PD law's recorded commands
   (``imitation_steps`` of behaviour cloning on the same windows) and starts from there.
4. **evaluate** on the held-out references through the open-loop environment (:func:`efficienttrack.envs.evaluate`,
   ``loop="open"``), scored by :func:`efficienttrack.data.metrics.compute_metrics`.

:func:`train_efficienttrack_open` runs this after 1, 2, 5, 10 … collection passes within the budget (the passes are
collected once, in order; each pass count trains from scratch on its first p passes, as the study's closed-loop
EfficientTrack runs one pipeline per pass count).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any, cast

import torch

from efficienttrack.baselines.agent import policy_act
from efficienttrack.baselines.curve import CURVE_FILE, CurveRecorder, TrainingRun, check_training_run, earlier_points
from efficienttrack.baselines.resume import references_digest
from efficienttrack.core.configfile import check_seed
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import output_lock
from efficienttrack.core.progress import ProgressDisplay
from efficienttrack.core.settings import DEVICE, canonical_preset, check_fields, inherit, setting
from efficienttrack.data.dataset import Sequences
from efficienttrack.data.records import EpisodeRecord
from efficienttrack.envs.core import open_system
from efficienttrack.learn.dynamics import NORM_SAMPLES, PlantModel, train_model
from efficienttrack.learn.nets import check_device_here, resolve_device
from efficienttrack.learn.policy import PWMPolicy, train_policy
from efficienttrack.learn.settings import MAX_STEPS, ModelConfig, PolicyConfig
from efficienttrack.workflow.collect import MAX_PASSES, CollectConfig, pass_counts, run_pass


@dataclass(frozen=True)
class OpenLoopSettings:
    """Settings of open-loop EfficientTrack: the closed loop's, with a plant model, a PWM policy and imitation."""

    model: ModelConfig = setting(
        default_factory=lambda: ModelConfig(history=5, steps=1000, batch_size=256, lr=1e-3, warmup=0.0, cosine_decay=True)
    )
    """The plant model g_θ and its training (the closed loop's ``cpu`` preset: history 5 = 0.25 s, horizon 20, 128 × 3
    units, weight decay 0.003 as in the paper; 1000 steps instead of 4000 to keep a pass count within minutes; the
    learning rate 1e-3 from the first step, as the open loop was measured: the closed loop's 3e-3 with a warm-up is not)."""
    policy: PolicyConfig = setting(
        default_factory=lambda: PolicyConfig(horizon=20, steps=500, lr=1e-3, warmup=0.0, imagined_share=0.0, row_cap=0.0)
    )
    """π_φ and its training: the paper's horizon 20, γ 0.98 and k_smooth 1.0; 128 × 3 units. ``k_smooth`` weighs the
    change of the command in (PWM / 1000)², as the research code's open loop does (docs/openloop.md measures 0.01
    against 1.0: with 0.01 the policy switches the valves between dead zone and full speed). ``imagined_share`` 0 and
    ``row_cap`` 0, the paper's loss: imagined deployments, the gradient's cap and the rate 3e-3 with a warm-up were
    measured in the closed loop only."""
    sigma_max: float = inherit(CollectConfig, "sigma_max", 0.05)
    """Collection: bound of the per-episode noise level on the PD reference, rad (the paper's 0.05, white in time as
    the open loop was measured; the closed loop's default is slower and larger)."""
    noise_ratio: tuple[float, float] = inherit(CollectConfig, "noise_ratio", (9.0, 2.0))
    """Collection: noisy : clean episodes (the paper's best, 9:2)."""
    imitation_steps: int = setting(500, ge=0, le=MAX_STEPS)
    """Behaviour-cloning steps that fit π_φ to the PD law's recorded commands before training through g_θ (ours; 0:
    start from u = 0). Same batch size and learning rate as the policy's training."""
    device: str = setting("cpu", pattern=DEVICE)
    """Torch device of the training (``auto``, ``cpu``, ``cuda``); evaluation runs the policy on the CPU."""

    def __post_init__(self) -> None:
        """Check the fields (:func:`~efficienttrack.core.settings.check_fields`), the noise mix (CollectConfig), the device."""
        check_fields(self)
        CollectConfig(sigma_max=self.sigma_max, noise_ratio=self.noise_ratio)
        check_device_here("OpenLoopSettings", self.device)


OPEN_PRESETS: dict[str, OpenLoopSettings] = {
    "cpu": OpenLoopSettings(),
    "tiny": OpenLoopSettings(
        model=ModelConfig(hidden=32, layers=2, horizon=4, history=None, batch_size=64, lr=3e-3, warmup=0.0, steps=100),
        policy=PolicyConfig(
            hidden=32, layers=2, horizon=4, batch_size=64, lr=3e-3, warmup=0.0, steps=60, imagined_share=0.0, row_cap=0.0
        ),
        imitation_steps=60,
    ),
}
"""``cpu``: minutes per pass count on a CPU; ``tiny``: seconds (tests; its curves say nothing about the method)."""


def open_settings(preset: str | OpenLoopSettings) -> OpenLoopSettings:
    """The settings by preset name (:data:`OPEN_PRESETS`), or ``preset`` itself.

    Args:
        preset: ``"cpu"``, ``"tiny"`` or an :class:`OpenLoopSettings`.
    """
    if isinstance(preset, OpenLoopSettings):
        return preset
    preset = canonical_preset(preset)
    if preset not in OPEN_PRESETS:
        raise EfficientTrackError(f"preset '{preset}': unknown for open-loop EfficientTrack ({', '.join(OPEN_PRESETS)})")
    return OPEN_PRESETS[preset]


def imitate(
    cfg: PolicyConfig, records: Sequence[EpisodeRecord], steps: int, seed: int, device: str | torch.device = "cpu"
) -> PWMPolicy:
    """Behaviour cloning: fit π_φ to the recorded commands, min ‖π_φ(o_H, u_H, q*_F) − u_t / 1000‖².

    Args:
        cfg: the policy's config (sizes, ``batch_size``, ``lr``).
        records: episodes with their PWM ``u``.
        steps: Adam steps (0: the fresh policy, u = 0, scaled on the records).
        seed: seeds the initialization and the window sampling.
        device: where to train.

    Returns:
        The policy (on ``device``), its feature scaling fitted on the records' windows.
    """
    device = resolve_device(device)
    torch.manual_seed(check_seed(seed, "seed"))
    F = cfg.future_length
    data = Sequences(records, history=cfg.history_length, future=F, device=device, channel="u")
    starts = data.starts(1)
    pi_phi = PWMPolicy(cfg).to(device)
    sample = data.window(starts[torch.randperm(len(starts))[:NORM_SAMPLES].to(device)], horizon=0, desired=F)
    pi_phi.fit_scaling(sample.obs_hist, sample.qref_hist, sample.qdes_future)
    optimizer = torch.optim.Adam(pi_phi.parameters(), lr=cfg.lr)
    generator = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        window = data.window(starts[torch.randint(len(starts), (cfg.batch_size,), generator=generator).to(device)], 1, F)
        # loss: the PD law's command u_t / 1000, recorded, as the target
        loss = (pi_phi(window.obs_hist, window.qref_hist, window.qdes_future) - window.qref_future[:, 0]).pow(2).sum(-1)
        optimizer.zero_grad(set_to_none=True)
        loss.mean().backward()
        optimizer.step()
    return pi_phi.eval()


def train_efficienttrack_open(
    run: TrainingRun, preset: str | OpenLoopSettings = "cpu", progress: ProgressDisplay | None = None
) -> list[dict[str, Any]]:
    """Open-loop EfficientTrack after 1, 2, 5, 10 … collection passes within the budget; the curve of its test metrics.

    The passes are collected once, in order, with the PD controller on ``system``'s closed loop (pass k's noise seeded
    by (seed, k), so p passes are the same whatever the budget); after p passes, a plant model and a PWM policy are
    trained from scratch on them (seeded by ``seed``) and the policy runs every test reference once on the plant, then
    every validation reference when the run has them. ``folder/curve.json`` is rewritten after each point; the same
    run started again in the folder keeps the points it finds there and trains only the pass counts still missing (the
    passes are collected again: they are the same).

    Args:
        run: the run (:func:`~efficienttrack.baselines.curve.training_run`): ``loop`` must be ``"open"`` (the closed
            loop is :func:`efficienttrack.workflow.pipeline.run_pipeline`); ``budget`` at least one pass over
            ``train_refs``; ``seed`` seeds the collection noise and the trainings; ``folder`` gets ``curve.json``;
            ``eval_at``: each count is measured after the most passes whose steps do not exceed it (at least one),
            None: the pass counts 1, 2, 5, 10 … that fit the budget (:func:`~efficienttrack.workflow.collect.pass_counts`).
        preset: ``"cpu"``, ``"tiny"`` (:data:`OPEN_PRESETS`) or an :class:`OpenLoopSettings`.
        progress: a display for the interaction count and the last MAE, or None.

    Returns:
        One point per pass count: ``{"interaction_steps": p · steps per pass, "wall_seconds": the collection of p passes
        plus the trainings, "metrics": compute_metrics of the test episodes, "passes": p}``, and ``"validation"``
        (compute_metrics of the validation episodes) when the run has validation references.

    Raises:
        EfficientTrackError: a run that is no TrainingRun or not in the open loop, a budget below one pass, an unknown
            preset, a folder being written by another process.
    """
    settings = open_settings(preset)
    run = check_training_run(run)
    if run.loop != "open":
        raise EfficientTrackError(f"loop '{run.loop}': open-loop EfficientTrack runs in the open loop only ('open')")
    steps_per_pass = sum(ref.steps for ref in run.train_refs)
    counts = pass_counts(run.budget, steps_per_pass)
    if not counts:
        raise EfficientTrackError(
            f"budget {run.budget}: less than one collection pass over the training references ({steps_per_pass} steps)"
        )
    if run.eval_at is not None:
        counts = sorted({min(max(1, point // steps_per_pass), MAX_PASSES) for point in run.eval_at})
    system, seed = run.system, run.seed
    plant = open_system("open", system)
    closed = system.open()
    collect_cfg = CollectConfig(
        sigma_max=settings.sigma_max, noise_ratio=settings.noise_ratio, noise_rho=0.0, passes=1, seed=seed
    )
    header = {"method": "efficienttrack", "loop": run.loop, "seed": seed, "budget": run.budget,
              "system": system.to_dict(), "settings": asdict(settings),
              "references": references_digest(*run.reference_sets)}  # fmt: skip
    records: list[EpisodeRecord] = []
    collect_seconds: list[float] = []
    with output_lock(run.folder / CURVE_FILE, "folder", folder=False):
        earlier = earlier_points(run.folder / CURVE_FILE, header)
        recorder = CurveRecorder(run, header, plant, progress)
        try:
            recorder.resume(earlier, 0.0, 0)  # its passes are collected again, from the first
            done = {point.get("passes") for point in earlier}
            for passes in (p for p in counts if p not in done):
                while len(collect_seconds) < passes:  # collect
                    began = time.perf_counter()
                    records += run_pass(closed, run.train_refs, collect_cfg, len(collect_seconds))
                    collect_seconds.append(time.perf_counter() - began)
                    recorder.show(len(collect_seconds) * steps_per_pass)
                began = time.perf_counter()
                policy, samples = train_open_loop(settings, records, seed)
                wall = sum(collect_seconds[:passes]) + time.perf_counter() - began
                extra = {"passes": passes, "gradient_samples": samples}
                recorder.measure(policy_act(policy, "open"), passes * steps_per_pass, wall, extra)
        finally:
            recorder.close()
    return recorder.curve


def train_open_loop(settings: OpenLoopSettings, records: Sequence[EpisodeRecord], seed: int) -> tuple[PWMPolicy, int]:
    """Steps 2 and 3 of the module docstring: the plant model, then the PWM policy through it (on the CPU at the end).

    Args:
        settings: the settings.
        records: the collected episodes, with their PWM ``u``.
        seed: seeds both trainings and the imitation.

    Returns:
        π_φ, in eval mode on the CPU, and the windows the three trainings' optimizer steps took (steps × batch).
    """
    model = train_model(settings.model, records, settings.device, seed, progress=False, network=PlantModel)
    init = imitate(settings.policy, records, settings.imitation_steps, seed, settings.device)
    policy = train_policy(
        settings.policy, model.model, records, settings.device, seed, progress=False, init=init, network=PWMPolicy
    )
    samples = (model.steps * settings.model.batch_size
               + (settings.imitation_steps + policy.steps) * settings.policy.batch_size)  # fmt: skip
    return cast(PWMPolicy, policy.policy.cpu().eval()), samples  # train_policy built a network=PWMPolicy

"""The settings of TD-MPC: one frozen dataclass, presets ``paper`` (the paper's TD-MPC config), ``cpu`` and ``tiny``.

``paper`` (the dataclass's defaults) is the configuration the paper gives for its TD-MPC baseline (Hansen et al.
2022), and the public TD-MPC code's defaults for what the paper leaves out (each field's docstring says which); on a
CPU it costs about a second per interaction step. ``cpu`` is "TD-MPC (reduced)": the same algorithm with a cheaper
planner, a smaller batch, narrower networks and shorter schedules, so that EfficientTrack's one pass
(17,672 interaction steps on the paper's simulator) takes about an hour on one CPU thread (docs/tdmpc.md says per
field what was reduced and why). ``tiny`` shrinks networks, samples, batches and the seeding phase so that a few
hundred interaction steps take seconds on a CPU (tests and smoke runs; its curves say nothing about the method).
"""

from __future__ import annotations

from dataclasses import dataclass

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.settings import DEVICE, canonical_preset, check_fields, setting

EVALUATE_WITH = ("policy", "plan")
"""How the curve's deterministic agent acts: π's mean action, or the planner without exploration noise."""


@dataclass(frozen=True)
class TDMPCSettings:
    """Settings of TD-MPC: the paper's TD-MPC config where it gives it, the public TD-MPC code's defaults otherwise."""

    horizon: int = setting(5, ge=1)
    """Planning horizon H, and the length of the sequences the TOLD model is trained on (paper: 5)."""
    iterations: int = setting(6, ge=1)
    """Planning iterations of the sampling planner per step (paper: 6)."""
    num_samples: int = setting(512, ge=1)
    """Action sequences sampled from the planner's Gaussian per iteration (paper: 512)."""
    num_elites: int = setting(64, ge=1)
    """Best sequences the new mean and standard deviation are fitted to (paper: 64)."""
    mixture_coef: float = setting(0.05, ge=0, le=1)
    """Share of extra sequences rolled out with π, ``int(mixture_coef · num_samples)`` of them (paper: 0.05)."""
    min_std: float = setting(0.05, gt=0, le=2)
    """Final lower bound of the planner's standard deviation, and π's noise in the TD target and π loss (paper: 0.05)."""
    std_start: float = setting(0.5, gt=0, le=2)
    """Lower bound of the planner's standard deviation at step 0, falling linearly to ``min_std`` over
    ``schedule_steps`` (public code: ``std_schedule: linear(0.5, min_std, 25000)``)."""
    horizon_start: int = setting(1, ge=1)
    """Planning horizon at step 0, rising linearly to ``horizon`` over ``schedule_steps`` (public code:
    ``horizon_schedule: linear(1, horizon, 25000)``)."""
    schedule_steps: int = setting(25_000, ge=1)
    """Interaction steps over which the two schedules above run (public code: 25,000)."""
    temperature: float = setting(0.5, gt=0)
    """Temperature of the elites' weights ``exp(temperature · (value − max value))`` (paper: 0.5)."""
    momentum: float = setting(0.1, ge=0, le=1)
    """Weight of the previous mean in each iteration's new mean (paper: 0.1)."""
    batch_size: int = setting(512, ge=1)
    """Sequences per update (paper: 512)."""
    buffer_size: int = setting(180_000, ge=1)
    """Replay buffer capacity in transitions (paper: 180,000)."""
    reward_coef: float = setting(0.5, ge=0)
    """Weight of the reward prediction loss (paper: 0.5)."""
    value_coef: float = setting(0.1, ge=0)
    """Weight of the Q (TD) loss (paper: 0.1)."""
    consistency_coef: float = setting(2.0, ge=0)
    """Weight of the latent consistency loss (paper: 2)."""
    rho: float = setting(0.5, ge=0, le=1)
    """ρ: the loss of horizon step t is weighted ρ^t (paper: 0.5)."""
    learning_rate: float = setting(1e-3, gt=0)
    """Adam learning rate of the model and of π (paper: 1e-3)."""
    grad_clip_norm: float = setting(10.0, gt=0)
    """Gradient-norm clip of both updates (public code: 10)."""
    seed_steps: int = setting(5_000, ge=0)
    """Interaction steps of uniformly random actions before planning; when they end, as many updates run at once, then
    one per interaction step (paper: 5,000; public code's update schedule)."""
    target_every: int = setting(2, ge=1)
    """Updates between two Polyak steps of the target network (paper: ``update_freq`` 2, the public code's period of
    the target update)."""
    tau: float = setting(0.01, ge=0, le=1)
    """Polyak coefficient of the target network (paper: 0.01)."""
    latent_dim: int = setting(50, ge=1)
    """Size of the latent state z (paper: 50)."""
    hidden: int = setting(512, ge=1)
    """Width of the hidden layers of dynamics, reward, π and Q (paper: MLPs 512 wide)."""
    encoder_hidden: int = setting(256, ge=1)
    """Width of the encoder's hidden layer (public code: ``enc_dim`` 256)."""
    discount: float = setting(0.98, ge=0, le=1)
    """Discount factor γ (paper: 0.98)."""
    per_alpha: float = setting(0.6, ge=0, le=1)
    """Prioritized replay: sequences are drawn with probability ∝ priority^α (paper: 0.6)."""
    per_beta: float = setting(0.4, ge=0, le=1)
    """Prioritized replay: importance weights (n · P(i))^−β, divided by their maximum (paper: 0.4)."""
    evaluate_with: str = setting("policy", choices=EVALUATE_WITH)
    """The curve's deterministic agent: ``"policy"`` (π's mean action, one network call for all test references) or
    ``"plan"`` (the planner without exploration noise, as the public code evaluates; vectorized over the test
    references, but about ``iterations · (num_samples + π samples)`` times the cost; see docs/tdmpc.md)."""
    inputs: str = setting("relative", choices=("relative", "raw"))
    """What the networks see: ``"relative"``, the standardized relative features every learner shares
    (:class:`~efficienttrack.envs.features.ObservationPipeline`), or ``"raw"``, the flat observation."""
    device: str = setting("auto", pattern=DEVICE)
    """Torch device: ``"auto"`` takes CUDA when present, else the CPU."""

    def __post_init__(self) -> None:
        """Check the fields (:func:`~efficienttrack.core.settings.check_fields`), then the horizons and the elites."""
        check_fields(self)
        if self.horizon_start > self.horizon:
            raise EfficientTrackError(
                f"TDMPCSettings.horizon_start must be ≤ horizon = {self.horizon}, got {self.horizon_start}"
            )
        if self.num_elites > self.num_samples + self.num_pi_samples:
            raise EfficientTrackError(
                f"TDMPCSettings.num_elites must be ≤ the sequences sampled ({self.num_samples + self.num_pi_samples}), "
                f"got {self.num_elites}"
            )
        if self.buffer_size < self.horizon:
            raise EfficientTrackError(
                f"TDMPCSettings.buffer_size must hold a sequence of horizon = {self.horizon} steps, got {self.buffer_size}"
            )

    @property
    def num_pi_samples(self) -> int:
        """Sequences rolled out with π and added to the planner's samples: ``int(mixture_coef · num_samples)``."""
        return int(self.mixture_coef * self.num_samples)

    def schedule(self, step: int) -> tuple[int, float]:
        """The planning horizon and the planner's lower bound on its standard deviation at interaction step ``step``.

        Args:
            step: interaction steps so far.

        Returns:
            ``(horizon, min_std)``: ``int(linear(horizon_start → horizon))`` and ``linear(std_start → min_std)``, each
            reaching its final value after ``schedule_steps`` steps.
        """
        mix = min(max(step / self.schedule_steps, 0.0), 1.0)
        horizon = int(min(self.horizon, (1 - mix) * self.horizon_start + mix * self.horizon))
        return horizon, (1 - mix) * self.std_start + mix * self.min_std


PRESETS: dict[str, TDMPCSettings] = {
    "paper": TDMPCSettings(),
    "cpu": TDMPCSettings(
        num_samples=256,
        num_elites=32,
        batch_size=256,
        hidden=256,
        schedule_steps=5_000,
    ),
    "tiny": TDMPCSettings(
        horizon=3,
        iterations=2,
        num_samples=32,
        num_elites=8,
        mixture_coef=0.125,
        batch_size=16,
        buffer_size=5_000,
        seed_steps=50,
        schedule_steps=200,
        latent_dim=8,
        hidden=32,
        encoder_hidden=32,
    ),
}
"""TD-MPC's presets: ``paper`` (the paper's TD-MPC config, about a CPU-second per interaction step: a GPU job),
``cpu`` ("TD-MPC (reduced)": half the planner's samples and elites, half the batch, hidden layers 256 wide instead of
512, and schedules of 5,000 steps instead of 25,000, so that they end with the seeding; about 0.18 s of CPU per
interaction step, so 17,672 steps take under an hour on one thread) and ``tiny`` (for tests and smoke runs)."""


def tdmpc_settings(preset: str | TDMPCSettings = "cpu") -> TDMPCSettings:
    """The settings by preset name, or ``preset`` itself when it is a :class:`TDMPCSettings`.

    Args:
        preset: ``"paper"``, ``"cpu"``, ``"tiny"`` or a :class:`TDMPCSettings`.

    Returns:
        The settings.

    Raises:
        EfficientTrackError: an unknown preset name or another type.
    """
    if isinstance(preset, TDMPCSettings):
        return preset
    if isinstance(preset, str):
        preset = canonical_preset(preset)
        if preset not in PRESETS:
            raise EfficientTrackError(f"preset '{preset}': unknown for tdmpc (known: {', '.join(PRESETS)})")
        return PRESETS[preset]
    raise EfficientTrackError(f"preset: tdmpc takes a preset name or TDMPCSettings, got {type(preset).__name__}")

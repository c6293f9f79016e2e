"""SuperTrack's settings: one frozen dataclass, presets ``cpu`` (minutes on a CPU) and ``tiny`` (seconds, tests)."""

from __future__ import annotations

from dataclasses import dataclass

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.settings import DEVICE, canonical_preset, check_fields, setting
from efficienttrack.learn.nets import check_device_here
from efficienttrack.learn.settings import MAX_STEPS, ModelConfig, PolicyConfig


@dataclass(frozen=True)
class SuperTrackSettings:
    """Settings of SuperTrack (Fussell et al. 2021) on the tracking environments.

    SuperTrack's own values where they carry over: the world model trained on windows of 8 steps, learning rate 1e-3
    for both networks, a constant rate (no schedule) as training never ends in an online method. The policy's window
    is SuperTrack's 32 in the paper; here it is 20, the most desired positions the environments show (F = 20).
    """

    model: ModelConfig = setting(
        default_factory=lambda: ModelConfig(
            horizon=8, history=5, steps=100, batch_size=256, lr=1e-3, warmup=0.0, cosine_decay=False
        )
    )
    """The world model g_θ (closed loop: of the PD loop; open loop: of the plant) and the optimizer steps it is trained
    per iteration (``steps``); horizon 8: SuperTrack's world-model window; history 5 as our closed loop's ``cpu``."""
    policy: PolicyConfig = setting(
        default_factory=lambda: PolicyConfig(
            horizon=20, steps=100, batch_size=128, lr=1e-3, warmup=0.0, cosine_decay=False, imagined_share=0.0, row_cap=0.0
        )
    )
    """π_φ and the optimizer steps it is trained per iteration (``steps``) through the world model on the discounted
    tracking loss plus k_smooth × the action's change (:func:`efficienttrack.learn.policy.train_policy`); its
    ``max_adjust`` is replaced by the system's bound in the closed loop and not used in the open loop;
    ``imagined_share`` 0 and ``row_cap`` 0: SuperTrack's loss on its world model's windows, without EfficientTrack's
    imagined deployments or its cap on the gradient."""
    steps_per_iteration: int = setting(4096, ge=1, le=MAX_STEPS)
    """Interaction steps collected per iteration (whole episodes on training references drawn at random, seeded)."""
    buffer_steps: int = setting(200_000, ge=1, le=100 * MAX_STEPS)
    """Replay buffer: the most recent episodes whose steps fit (older ones are dropped)."""
    noise_closed: float = setting(0.1, ge=0)
    """Exploration noise σ in the closed loop, in action units (× the adjustment bound: 10 % of it)."""
    noise_open: float = setting(0.3, ge=0)
    """Exploration noise σ in the open loop, in action units (PWM / 1000: 300 PWM, enough to leave the valves' dead
    zone, so that the first iteration, with the policy still at u = 0, moves the machine)."""
    noise_rho: float = setting(0.9, ge=0, lt=1)
    """Correlation of consecutive noise steps (AR(1)): slow noise moves a hydraulic joint, white noise averages out."""
    device: str = setting("cpu", pattern=DEVICE)
    """Torch device of the training (``auto``, ``cpu``, ``cuda``); collection and evaluation run the policy on the CPU."""

    def __post_init__(self) -> None:
        """Check the fields (:func:`~efficienttrack.core.settings.check_fields`), then that the device is on this machine."""
        check_fields(self)
        check_device_here("SuperTrackSettings", self.device)

    def noise(self, loop: str) -> float:
        """The exploration σ of ``loop`` (``"closed"`` or ``"open"``), in action units.

        Args:
            loop: the loop.
        """
        return self.noise_open if loop == "open" else self.noise_closed


SUPERTRACK_PRESETS: dict[str, SuperTrackSettings] = {
    "cpu": SuperTrackSettings(),
    "tiny": SuperTrackSettings(
        model=ModelConfig(
            hidden=32, layers=2, horizon=4, history=3, batch_size=64, steps=20, lr=3e-3, warmup=0.0, cosine_decay=False
        ),
        policy=PolicyConfig(
            hidden=32, layers=2, horizon=4, batch_size=64, steps=20, lr=3e-3, warmup=0.0, cosine_decay=False,
            imagined_share=0.0, row_cap=0.0,
        ),
        steps_per_iteration=1000,
        buffer_steps=20_000,
    ),
}  # fmt: skip
"""``cpu``: minutes per 50,000 interaction steps on a CPU; ``tiny``: seconds (tests; its curves say nothing)."""


def supertrack_settings(preset: str | SuperTrackSettings) -> SuperTrackSettings:
    """The settings by preset name (:data:`SUPERTRACK_PRESETS`), or ``preset`` itself.

    Args:
        preset: ``"cpu"``, ``"tiny"`` or a :class:`SuperTrackSettings`.
    """
    if isinstance(preset, SuperTrackSettings):
        return preset
    preset = canonical_preset(preset)
    if preset not in SUPERTRACK_PRESETS:
        raise EfficientTrackError(f"preset '{preset}': unknown for supertrack (known: {', '.join(SUPERTRACK_PRESETS)})")
    return SUPERTRACK_PRESETS[preset]

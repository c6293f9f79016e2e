"""The paper's Table I (its simulator, its 8 test references): the rows a study on ``--system paper`` prints beside its own.

Transcribed from Zou et al. (2025), Table I, "Metrics of Comparative Experiments in Simulation"; I.T. is I.S. at 20 Hz
(PPO's is the paper's sum over its 16 parallel workers). Metrics in degrees, ETD in cm.
"""

from __future__ import annotations

from typing import Any

from efficienttrack.data.metrics import interaction_hours

_FIELDS = ("interaction_steps", "smt1_deg", "smt2_deg", "mae_deg", "rmse_deg", "fmae_deg", "etd_mae_cm", "etd_fmae_cm")
_ROWS: dict[tuple[str, str], tuple[float | None, ...]] = {
    ("pd", "closed"): (None, 0.67, 0.70, 2.73, 3.14, 2.93, 14.73, 11.25),
    ("ppo", "open"): (12_361_696, 3.28, 2.91, 24.94, 28.82, 19.80, 183.45, 200.82),
    ("sac", "open"): (486_858, 1.43, 1.67, 2.78, 3.68, 5.85, 34.80, 70.82),
    ("tdmpc", "open"): (241_468, 1.35, 1.69, 1.66, 2.18, 1.15, 17.33, 12.66),
    ("supertrack", "open"): (543_620, 0.75, 0.84, 0.58, 0.82, 0.46, 6.74, 5.97),
    ("efficienttrack", "open"): (176_720, 0.76, 0.63, 0.53, 0.92, 0.45, 5.19, 3.86),
    ("ppo", "closed"): (10_590_994, 0.70, 0.76, 4.45, 5.15, 5.11, 61.57, 50.47),
    ("sac", "closed"): (442_892, 1.10, 1.38, 1.54, 2.18, 3.84, 14.92, 50.90),
    ("tdmpc", "closed"): (197_890, 0.94, 1.13, 0.60, 0.80, 0.49, 7.99, 5.90),
    ("supertrack", "closed"): (523_541, 0.71, 0.73, 0.34, 0.49, 0.36, 3.96, 3.64),
    ("efficienttrack", "closed"): (176_720, 0.67, 0.59, 0.32, 0.46, 0.23, 3.94, 2.00),
}


def paper_row(method: str, loop: str) -> dict[str, Any] | None:
    """The paper's Table I row of a method in a loop (the PD row in either loop), or None when the paper has none.

    Args:
        method: a method name of :data:`efficienttrack.study.methods.METHODS` (``pd``, ``efficienttrack``, ``sac``…).
        loop: ``closed`` or ``open``.

    Returns:
        ``{"interaction_steps", "interaction_hours", "smt1_deg", "smt2_deg", "mae_deg", "rmse_deg", "fmae_deg",
        "etd_mae_cm", "etd_fmae_cm"}`` (steps and hours None for PD).
    """
    values = _ROWS.get((method, "closed" if method == "pd" else loop))
    if values is None:
        return None
    row = dict(zip(_FIELDS, values, strict=True))
    steps = row["interaction_steps"]
    row["interaction_hours"] = None if steps is None else interaction_hours(int(steps))
    return row


def is_paper_system(system: dict[str, Any]) -> bool:
    """Whether a study's system is the paper's simulator under its own PD law, the setting of Table I.

    Args:
        system: the spec's dict (:meth:`~efficienttrack.systems.spec.SystemSpec.to_dict`), as ``study_config.json``
            records it.
    """
    if system.get("options") or system.get("limits"):
        return False
    return system.get("system") == "paper" or (system.get("plant") == "paper" and system.get("pd") == "paper")

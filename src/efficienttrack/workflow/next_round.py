"""One round of continual learning on a deployed machine: π_{k−1} was deployed and recorded; train round k from it.

The paper improves a deployed policy in rounds: deploy π_{k−1}, record its episodes, then train the model g_θk and
the policy π_φk starting from θ_{k−1}, φ_{k−1} (a warm start, with their feature scaling) on the new records, or on
the new and the earlier ones together. :func:`next_round` does that and reports how much the round changed:

- the model's 20-step prediction error (MPE, :func:`~efficienttrack.learn.dynamics.model_error`) on the new records
  before (θ_{k−1}) and after (θ_k): the new records are driven by π_{k−1}, which the previous model never saw;
- the same on held-out records, when given (records not trained on, e.g. another policy's logs);
- the tracking error recorded in the new records (what π_{k−1} achieved on the machine), and the model-predicted
  tracking error (:func:`~efficienttrack.learn.policy.predicted_tracking_error`, through θ_k from the new records' windows)
  of the position controller alone, of π_{k−1} and of π_k.

A warm-started network keeps its sizes: the config of round k is the previous network's, with the training
schedule (optimizer steps, learning rate, batch, decay; the :class:`~efficienttrack.learn.settings.TrainingSchedule`
fields) taken from the config given for the round (:func:`continued_config`).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple, TypeVar

import torch

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import write_json
from efficienttrack.core.provenance import provenance
from efficienttrack.data.metrics import compute_metrics
from efficienttrack.data.records import EpisodeRecord
from efficienttrack.learn.dynamics import MPE_STEPS, ClosedLoopModel, model_error, save_model, train_model
from efficienttrack.learn.nets import resolve_device
from efficienttrack.learn.policy import AdjustmentPolicy, predicted_tracking_error, save_policy, train_policy
from efficienttrack.learn.settings import ModelConfig, PolicyConfig, TrainingSchedule

ConfigT = TypeVar("ConfigT", bound=TrainingSchedule)

ROUND_JSON = "round.json"
"""The report a round writes into its folder (:meth:`RoundReport.to_json` with provenance and the inputs)."""
ROUND_OUTPUTS = (
    "model.pt",
    "model.json",
    "model.state.pt",
    "model.logs",
    "policy.pt",
    "policy.json",
    "policy.state.pt",
    "policy.logs",
    ROUND_JSON,
)
"""Names :func:`next_round` writes into its folder (checkpoints, training states, scalar logs, the report)."""


def continued_config(schedule: ConfigT, network: ConfigT) -> ConfigT:
    """The config of a warm-started run: ``network``'s sizes and loss, ``schedule``'s training schedule.

    Args:
        schedule: a config (e.g. a preset) whose :class:`~efficienttrack.learn.settings.TrainingSchedule` fields
            (steps, epochs, lr, batch_size, weight_decay, cosine_decay, grad_clip, save_every, eval_every) are used.
        network: the config of the network the run starts from; every other field (hidden, layers, horizon,
            history, and for a policy gamma, k_smooth, max_adjust) is kept, so its weights fit.

    Returns:
        A config of ``network``'s class.

    Raises:
        EfficientTrackError: the two configs are of different classes.
    """
    if type(schedule) is not type(network):
        raise EfficientTrackError(f"continued_config: a {type(schedule).__name__} cannot continue a {type(network).__name__}")
    fields = {field.name: getattr(schedule, field.name) for field in dataclasses.fields(TrainingSchedule)}
    return dataclasses.replace(network, **fields)


class RoundReport(NamedTuple):
    """What a round changed, degrees (joints pooled). "before": round k−1's networks, "after": round k's.

    Attributes:
        new_episodes: episodes recorded with π_{k−1} deployed (the round's new data).
        old_episodes: earlier episodes trained on with them (0: new data only).
        model_steps: optimizer steps of the model's training.
        policy_steps: optimizer steps of the policy's training.
        model_mpe_before_deg: 20-step MPE of g_θ(k−1) on the new episodes.
        model_mpe_after_deg: 20-step MPE of g_θk on the new episodes (trained on).
        held_out_mpe_before_deg: 20-step MPE of g_θ(k−1) on the held-out episodes (None without).
        held_out_mpe_after_deg: 20-step MPE of g_θk on the held-out episodes (None without).
        recorded_mae_deg: tracking MAE recorded in the new episodes (π_{k−1} on the machine).
        predicted_pd_deg: tracking error predicted by g_θk from the new episodes' windows with a = 0.
        predicted_before_deg: the same under π_{k−1}.
        predicted_after_deg: the same under π_k.
        seconds: wall time of the round.
    """

    new_episodes: int
    old_episodes: int
    model_steps: int
    policy_steps: int
    model_mpe_before_deg: float
    model_mpe_after_deg: float
    held_out_mpe_before_deg: float | None
    held_out_mpe_after_deg: float | None
    recorded_mae_deg: float
    predicted_pd_deg: float
    predicted_before_deg: float
    predicted_after_deg: float
    seconds: float

    def to_json(self) -> dict[str, Any]:
        """The report as a JSON object (field → value)."""
        return self._asdict()


class RoundResult(NamedTuple):
    """Outcome of :func:`next_round`.

    Attributes:
        model: g_θk (eval mode, on the round's device).
        policy: π_φk (eval mode, on the round's device).
        report: the errors before and after.
    """

    model: ClosedLoopModel
    policy: AdjustmentPolicy
    report: RoundReport


def next_round(
    model: ClosedLoopModel,
    policy: AdjustmentPolicy,
    new_records: Sequence[EpisodeRecord],
    old_records: Sequence[EpisodeRecord] = (),
    model_schedule: ModelConfig | None = None,
    policy_schedule: PolicyConfig | None = None,
    device: str | torch.device = "auto",
    seed: int = 0,
    out_dir: str | Path | None = None,
    held_out: Sequence[EpisodeRecord] = (),
    progress: bool = True,
    inputs: Mapping[str, Any] | None = None,
) -> RoundResult:
    """Round k: train g_θk from ``model`` and then π_φk from ``policy`` through g_θk, on the new (and old) records.

    Both trainings start from the given networks (weights and feature scaling,
    :func:`~efficienttrack.learn.checkpoints.warm_start`) and see the same episodes: ``new_records`` followed by
    ``old_records``. The policy's windows start the model rollouts it is trained through.

    Args:
        model: g_θ(k−1), the model of the previous round.
        policy: π_φ(k−1), the policy deployed while ``new_records`` were recorded.
        new_records: episodes recorded with ``policy`` deployed (at least one).
        old_records: earlier episodes to train on as well (e.g. the PD data of round 1); empty: new data only.
        model_schedule: the model's training schedule (its TrainingSchedule fields; sizes are ``model``'s, see
            :func:`continued_config`); None: ``model.cfg``'s own.
        policy_schedule: the policy's training schedule, likewise; None: ``policy.cfg``'s own.
        device: ``"auto"``, ``"cpu"``, ``"cuda"``.
        seed: seeds both trainings' initialization and window sampling.
        out_dir: folder to write the round into (:data:`ROUND_OUTPUTS`: ``model.pt``, ``policy.pt`` with their JSON
            configs, training states that an interrupted round resumes from, scalar logs ``model.logs/``,
            ``policy.logs/``, and :data:`ROUND_JSON`); None writes nothing.
        held_out: episodes not trained on: their MPE before and after is reported, and logged during training.
        progress: show progress bars.
        inputs: JSON-serializable facts about the inputs (e.g. checkpoint and data paths) stored in ``round.json``.

    Returns:
        The new model and policy and the report.

    Raises:
        EfficientTrackError: no new records.
    """
    if not new_records:
        raise EfficientTrackError("next_round: no new episodes (record the deployed policy first)")
    started = time.perf_counter()
    device = resolve_device(device)
    folder = None if out_dir is None else Path(out_dir)
    records = [*new_records, *old_records]
    model_cfg = continued_config(model_schedule or model.cfg, model.cfg)
    policy_cfg = continued_config(policy_schedule or policy.cfg, policy.cfg)

    def path(name: str) -> Path | None:
        return None if folder is None else folder / name

    trained_model = train_model(
        model_cfg, records, device, seed, progress, path("model.state.pt"), path("model.logs"), held_out, init=model
    )
    new_model = trained_model.model
    if folder is not None:
        save_model(new_model, folder / "model.pt", trained_model.fingerprint)
    trained_policy = train_policy(
        policy_cfg, new_model, records, device, seed, progress, path("policy.state.pt"), path("policy.logs"), held_out,
        init=policy,
    )  # fmt: skip
    new_policy = trained_policy.policy
    if folder is not None:
        save_policy(new_policy, folder / "policy.pt", trained_policy.fingerprint)

    def mpe(network: ClosedLoopModel, episodes: Sequence[EpisodeRecord]) -> float:
        return model_error(network, episodes, MPE_STEPS, device).mpe_deg

    def held_out_mpe(network: ClosedLoopModel) -> float | None:
        return mpe(network, held_out) if held_out else None

    def predicted(pi: AdjustmentPolicy | None) -> float:
        return predicted_tracking_error(new_model, new_records, pi, policy_cfg.rollout_length, device).mae_deg

    report = RoundReport(
        new_episodes=len(new_records),
        old_episodes=len(old_records),
        model_steps=trained_model.steps,
        policy_steps=trained_policy.steps,
        model_mpe_before_deg=mpe(model, new_records),  # new_records is not empty (checked above)
        model_mpe_after_deg=mpe(new_model, new_records),
        held_out_mpe_before_deg=held_out_mpe(model),
        held_out_mpe_after_deg=held_out_mpe(new_model),
        recorded_mae_deg=compute_metrics(new_records)["mae_deg"],
        predicted_pd_deg=predicted(None),
        predicted_before_deg=predicted(policy),
        predicted_after_deg=predicted(new_policy),
        seconds=round(time.perf_counter() - started, 2),
    )
    if folder is not None:
        write_json(
            folder / ROUND_JSON,
            {**report.to_json(), "inputs": dict(inputs or {}), "provenance": provenance(device, report.seconds)},
        )
    return RoundResult(new_model, new_policy, report)

"""Commands that train and measure the networks: ``train-model``, ``model-error``, ``train-policy``, ``round``."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from efficienttrack.cli.common import (
    ConfigOpt,
    DeviceOpt,
    PresetOpt,
    RecursiveOpt,
    RunDeviceOpt,
    RunSeedOpt,
    SetOpt,
    ThreadsOpt,
    _lock,
    _set_threads,
    _settings,
    app,
)
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import check_output_file, check_output_folder, finite_json, prepare_output_folder
from efficienttrack.data.metrics import MPE_STEPS
from efficienttrack.data.records import load_records

DataOpt = Annotated[
    list[Path], typer.Option("--data", help="Episode files or folders (repeatable; a folder's own episodes, see --recursive).")
]

TrainForceOpt = Annotated[
    bool, typer.Option("--force", help="Start afresh: delete the training state (OUT with .state.pt) instead of resuming it.")
]

StepsOpt = Annotated[int | None, typer.Option("--steps", help="Override the preset's number of optimizer steps.")]

HeldOutOpt = Annotated[
    list[Path] | None,
    typer.Option("--held-out", help="Episodes not trained on, for the held-out figure in the logs (repeatable)."),
]

InitModelOpt = Annotated[
    Path | None,
    typer.Option(
        "--init-model",
        help="Start from this model checkpoint (weights and scaling; its sizes, the preset's schedule): a round's warm start.",
    ),
]

InitPolicyOpt = Annotated[
    Path | None,
    typer.Option(
        "--init-policy",
        help="Start from this policy checkpoint (weights, scaling; its sizes, the preset's schedule): a round's warm start.",
    ),
]


def _check_checkpoint(out: Path) -> None:
    """Check that checkpoint ``out`` (a ``.pt``) and its log folder (``OUT`` with ``.logs``) can be written."""
    from efficienttrack.learn.checkpoints import check_checkpoint_path

    check_output_file(out)
    check_checkpoint_path(out)
    check_output_folder(out.with_suffix(".logs"))


def _training_state(out: Path, force: bool) -> Path:
    """The training-state file next to checkpoint ``out``, deleted first when ``force``."""
    state = out.with_suffix(".state.pt")
    if force:
        state.unlink(missing_ok=True)
    return state


def _schedule(cfg, steps: int | None, share: float = 1.0):
    """A model or policy config with ``steps`` optimizer steps when given (``--steps``), else scaled by ``share``."""
    import dataclasses

    return cfg.scaled(share) if steps is None else dataclasses.replace(cfg, steps=steps, epochs=None)


def _warm_start(option: str, path: Path | None, load, cfg, device: str):
    """Load the checkpoint given to ``option`` (None: a cold start) and the config to continue it with.

    Returns ``(network or None, config)``: the network's own sizes and loss, the schedule of ``cfg`` (the preset).
    """
    from efficienttrack.workflow.next_round import continued_config

    if path is None:
        return None, cfg
    try:
        network = load(path, device)
    except EfficientTrackError as exc:
        raise EfficientTrackError(f"{option}: {exc}") from exc
    typer.echo(f"warm start from {path}: its sizes ({network.cfg.hidden}×{network.cfg.layers}), the preset's schedule")
    return network, continued_config(cfg, network.cfg)


@app.command("train-model")
def train_model_command(
    ctx: typer.Context,
    data: DataOpt,
    out: Annotated[
        Path, typer.Option("--out", help="Model checkpoint (model.pt; config to model.json, scalar logs to model.logs/).")
    ],
    preset_name: PresetOpt = "cpu",
    config: ConfigOpt = None,
    overrides: SetOpt = None,
    steps: StepsOpt = None,
    held_out: HeldOutOpt = None,
    init_model: InitModelOpt = None,
    device: RunDeviceOpt = None,
    seed: RunSeedOpt = None,
    threads: ThreadsOpt = 1,
    recursive: RecursiveOpt = False,
    force: TrainForceOpt = False,
) -> None:
    """Train the closed-loop dynamics model on records (multi-step BPTT); an interrupted run resumes.

    The settings are the tree's ``model`` section, ``seed`` and ``device`` (``efficienttrack config show``).
    """
    from efficienttrack.learn.dynamics import load_model, save_model, train_model

    _check_checkpoint(out)
    _set_threads(threads)
    settings = _settings(preset_name, config, overrides, seed=seed, device=device)
    init, cfg = _warm_start("--init-model", init_model, load_model, _schedule(settings.model, steps), settings.device)
    records, held = load_records(data, recursive), load_records(held_out, recursive) if held_out else []
    logs = out.with_suffix(".logs")
    _lock(ctx, out, folder=False)
    state = _training_state(out, force)
    result = train_model(cfg, records, settings.device, settings.seed, True, state, logs, held, init)
    save_model(result.model, out, result.fingerprint)
    typer.echo(
        f"trained model on {result.windows} windows ({sum(map(len, records))} steps), {result.steps} steps in "
        f"{result.seconds:.0f} s, final loss {result.losses[-1]:.4g}; saved {out}, logs in {logs}"
    )


@app.command("model-error")
def model_error_command(
    model: Annotated[Path, typer.Option("--model", help="Model checkpoint (model.pt).")],
    data: DataOpt,
    steps: Annotated[int, typer.Option("--steps", help="Prediction horizon (default: the paper's 20 steps).")] = MPE_STEPS,
    device: DeviceOpt = "auto",
    json_output: Annotated[bool, typer.Option("--json", help="Print one JSON line.")] = False,
    threads: ThreadsOpt = 1,
    recursive: RecursiveOpt = False,
) -> None:
    """Multi-step model prediction error (MPE, the paper's Tr.MPE/Te.MPE) on records, degrees."""
    from efficienttrack.learn.dynamics import load_model, model_error

    _set_threads(threads)
    result = model_error(load_model(model, device), load_records(data, recursive), steps)
    if json_output:
        typer.echo(json.dumps(finite_json(result._asdict(), "model-error"), allow_nan=False))
        return
    joints = ", ".join(f"{v:.3f}" for v in result.per_joint_deg)
    typer.echo(f"MPE {result.mpe_deg:.3f}° over {result.windows} windows × {steps} steps; per joint {joints}°")


@app.command("train-policy")
def train_policy_command(
    ctx: typer.Context,
    model: Annotated[Path, typer.Option("--model", help="Model checkpoint (model.pt) to train through.")],
    data: DataOpt,
    out: Annotated[
        Path, typer.Option("--out", help="Policy checkpoint (policy.pt; config to policy.json, scalar logs to policy.logs/).")
    ],
    preset_name: PresetOpt = "cpu",
    config: ConfigOpt = None,
    overrides: SetOpt = None,
    steps: StepsOpt = None,
    held_out: HeldOutOpt = None,
    init_policy: InitPolicyOpt = None,
    device: RunDeviceOpt = None,
    seed: RunSeedOpt = None,
    threads: ThreadsOpt = 1,
    recursive: RecursiveOpt = False,
    force: TrainForceOpt = False,
) -> None:
    """Train the adjustment policy through the frozen model (multi-step BPTT); an interrupted run resumes.

    The settings are the tree's ``policy`` section, ``seed`` and ``device`` (``efficienttrack config show``).
    """
    from efficienttrack.learn.dynamics import load_model
    from efficienttrack.learn.policy import load_policy, predicted_tracking_error, save_policy, train_policy

    _check_checkpoint(out)
    _set_threads(threads)
    settings = _settings(preset_name, config, overrides, seed=seed, device=device)
    device = settings.device
    init, cfg = _warm_start("--init-policy", init_policy, load_policy, _schedule(settings.policy, steps), device)
    g_theta, records = load_model(model, device), load_records(data, recursive)
    held, logs = load_records(held_out, recursive) if held_out else [], out.with_suffix(".logs")
    _lock(ctx, out, folder=False)
    state = _training_state(out, force)
    result = train_policy(cfg, g_theta, records, device, settings.seed, True, state, logs, held, init)
    save_policy(result.policy, out, result.fingerprint)
    before = predicted_tracking_error(g_theta, records, None, cfg.rollout_length)
    after = predicted_tracking_error(g_theta, records, result.policy, cfg.rollout_length)
    typer.echo(
        f"trained policy, {result.steps} steps in {result.seconds:.0f} s; model-predicted tracking error "
        f"{before.mae_deg:.3f}° (a = 0) → {after.mae_deg:.3f}°; saved {out}, logs in {logs}"
    )


@app.command("round")
def round_command(
    ctx: typer.Context,
    model: Annotated[Path, typer.Option("--model", help="The previous round's model checkpoint (model.pt).")],
    policy: Annotated[Path, typer.Option("--policy", help="The previous round's policy checkpoint, the one deployed.")],
    data: Annotated[
        list[Path], typer.Option("--data", help="Episodes recorded with --policy deployed: the new data (repeatable).")
    ],
    out: Annotated[
        Path,
        typer.Option("--out", help="Folder for the round: model.pt, policy.pt (+ .json), their logs, round.json."),
    ],
    old_data: Annotated[
        list[Path] | None, typer.Option("--old-data", help="Earlier episodes to train on as well (repeatable).")
    ] = None,
    held_out: HeldOutOpt = None,
    preset_name: PresetOpt = "cpu",
    config: ConfigOpt = None,
    overrides: SetOpt = None,
    steps_model: Annotated[int | None, typer.Option("--steps-model", help="Override the model's optimizer steps.")] = None,
    steps_policy: Annotated[int | None, typer.Option("--steps-policy", help="Override the policy's optimizer steps.")] = None,
    warm_budget: Annotated[
        float | None,
        typer.Option(
            "--warm-budget", help="Share of the settings' optimizer steps a warm round trains (as run --rounds; default 0.5)."
        ),
    ] = None,
    device: RunDeviceOpt = None,
    seed: RunSeedOpt = None,
    threads: ThreadsOpt = 1,
    recursive: RecursiveOpt = False,
    force: Annotated[
        bool,
        typer.Option(
            "--force",
            help="Start afresh: delete an earlier round's outputs in OUT (other files are kept) instead of refusing it.",
        ),
    ] = False,
) -> None:
    """One round of continual learning: model and policy of round k from round k−1's and the newly recorded episodes.

    Both start from the given checkpoints (warm start): their sizes, the settings' schedules scaled by
    ``warm_budget``, the learning rates ramped over ``round_warmup`` of the steps. Prints and writes OUT/round.json: the
    model's 20-step error on the new episodes (and on --held-out) before and after, and the tracking error recorded and
    model-predicted.
    An interrupted round resumes (rerun the same command); a finished one is refused without --force.
    """
    import dataclasses

    from efficienttrack.learn.dynamics import load_model
    from efficienttrack.learn.policy import load_policy
    from efficienttrack.workflow.next_round import ROUND_JSON, ROUND_OUTPUTS, next_round

    check_output_folder(out)
    _set_threads(threads)
    settings = _settings(preset_name, config, overrides, seed=seed, device=device, warm_budget=warm_budget)
    seed, device = settings.seed, settings.device
    ramp = settings.round_warmup  # as a later round of `run --rounds`
    model_schedule = dataclasses.replace(_schedule(settings.model, steps_model, settings.warm_budget), warmup=ramp)
    policy_schedule = dataclasses.replace(_schedule(settings.policy, steps_policy, settings.warm_budget), warmup=ramp)
    g_theta, _ = _warm_start("--model", model, load_model, model_schedule, device)
    pi_phi, _ = _warm_start("--policy", policy, load_policy, policy_schedule, device)
    new, old = load_records(data, recursive), load_records(old_data, recursive) if old_data else []
    held = load_records(held_out, recursive) if held_out else []
    _lock(ctx, out)
    interrupted = out.is_dir() and not (out / ROUND_JSON).exists() and all(e.name in ROUND_OUTPUTS for e in out.iterdir())
    if force or not interrupted:
        prepare_output_folder(out, ROUND_OUTPUTS, force)
    inputs = {
        "model": str(model.resolve()),
        "policy": str(policy.resolve()),
        "data": [str(p.resolve()) for p in data],
        "old_data": [str(p.resolve()) for p in old_data or []],
        "held_out": [str(p.resolve()) for p in held_out or []],
        "preset": preset_name,
        "seed": seed,
    }
    report = next_round(
        g_theta, pi_phi, new, old, model_schedule, policy_schedule, device, seed, out, held, inputs=inputs
    ).report
    typer.echo(
        f"round on {report.new_episodes} new + {report.old_episodes} old episodes ({report.model_steps} model, "
        f"{report.policy_steps} policy steps, {report.seconds:.0f} s)\n"
        f"model 20-step MPE on the new episodes: {report.model_mpe_before_deg:.3f}° → {report.model_mpe_after_deg:.3f}°"
    )
    if report.held_out_mpe_before_deg is not None:
        typer.echo(f"model 20-step MPE held out: {report.held_out_mpe_before_deg:.3f}° → {report.held_out_mpe_after_deg:.3f}°")
    typer.echo(
        f"tracking MAE recorded with --policy: {report.recorded_mae_deg:.3f}°; predicted by the new model: a = 0 "
        f"{report.predicted_pd_deg:.3f}°, --policy {report.predicted_before_deg:.3f}°, new policy "
        f"{report.predicted_after_deg:.3f}°\nwrote {out / 'model.pt'}, {out / 'policy.pt'}, {out / ROUND_JSON}"
    )

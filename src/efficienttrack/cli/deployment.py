"""Commands that take a trained policy to a machine: ``export`` (ONNX) and ``deploy`` (the fixed-rate loop)."""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path
from typing import Annotated

import typer

from efficienttrack.cli.common import (
    ArmOpt,
    BetweenOpt,
    FastOpt,
    LimitsOpt,
    MachineOpt,
    MachineOpts,
    PdOpt,
    PlantOpt,
    SystemOpt,
    SystemOpts,
    _lock,
    _system_spec,
    app,
    between,
    parse_options,
)
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import check_output_folder, prepare_output_folder
from efficienttrack.deploy.loop import LoopConfig

LOOP = LoopConfig()
"""Where the ``deploy`` options take their defaults from."""


@app.command("export")
def export_command(
    ctx: typer.Context,
    policy: Annotated[Path, typer.Option("--policy", help="Policy checkpoint (policy.pt) to export.")],
    out: Annotated[Path, typer.Option("--out", help="Export folder: policy.onnx and its contract policy.json.")],
    force: Annotated[bool, typer.Option("--force", help="Replace an earlier export in OUT (other files are kept).")] = False,
) -> None:
    """Export a trained policy to ONNX (policy.onnx) with its contract (policy.json), for the torch-free runtime."""
    from efficienttrack.deploy.export import checkpoint_source, export_policy
    from efficienttrack.deploy.onnx_runtime import CONTRACT_FILE, ONNX_FILE
    from efficienttrack.learn.policy import load_policy

    check_output_folder(out)
    pi_phi = load_policy(policy, "cpu")
    _lock(ctx, out, resumable=False)
    prepare_output_folder(out, (ONNX_FILE, CONTRACT_FILE), force)
    export_policy(pi_phi, out, checkpoint_source(policy))
    typer.echo(f"exported {policy} to {out / ONNX_FILE} with its contract {out / CONTRACT_FILE}")


@app.command("deploy")
def deploy_command(
    ctx: typer.Context,
    refs: Annotated[Path, typer.Option("--refs", help="Folder of reference trajectories (.npy/.csv, rad), run in turn.")],
    out: Annotated[
        Path, typer.Option("--out", help="Output folder: <reference>.jsonl per run (a line per tick), deploy.json, records/.")
    ],
    policy: Annotated[
        Path | None,
        typer.Option(
            "--policy",
            help="Policy checkpoint (policy.pt), or an export folder (policy.onnx + policy.json, run in ONNX Runtime on the "
            "CPU); without, the raw reference (a = 0).",
        ),
    ] = None,
    arm: ArmOpt = False,
    shadow: Annotated[
        bool, typer.Option("--shadow", help="Compute and log the adjustment, send the raw reference (run this first).")
    ] = False,
    system: SystemOpt = None,
    plant: PlantOpt = None,
    pd: PdOpt = None,
    system_opt: SystemOpts = None,
    limits: LimitsOpt = None,
    machine: MachineOpt = None,
    machine_opt: MachineOpts = None,
    between_episodes: BetweenOpt = "approach",
    fast: FastOpt = False,
    hold_after: Annotated[int, typer.Option("--hold-after", help="Overruns in a row from which a = 0.")] = LOOP.hold_after,
    stop_after: Annotated[int, typer.Option("--stop-after", help="Overruns in a row that stop the run.")] = LOOP.stop_after,
    stale_ticks: Annotated[
        float, typer.Option("--stale-ticks", help="A reading older than this many periods: a = 0.")
    ] = LOOP.stale_ticks,
    stop_stale_ticks: Annotated[
        float, typer.Option("--stop-stale-ticks", help="The last good reading older than this many periods: stop.")
    ] = LOOP.stop_stale_ticks,
    accept_worse: Annotated[
        bool,
        typer.Option(
            "--accept-worse",
            help="Arm a policy whose recorded evaluation tracked worse than PD, or that is unproven (never evaluated, no "
            "shadow run): refused without.",
        ),
    ] = False,
    device: Annotated[str, typer.Option("--device", help="cpu, cuda or auto.")] = "cpu",
    force: Annotated[
        bool, typer.Option("--force", help="Start afresh in a non-empty OUT: first delete its logs, records and deploy.json.")
    ] = False,
) -> None:
    """The policy at 20 Hz on absolute deadlines against the simulator or a machine, with watchdogs; a log per tick.

    Nothing is sent without --arm, because even shadow mode moves the machine (along the raw reference). Start with
    --arm --shadow; every run starts and ends with a = 0. Exit code 1 when a watchdog stopped a run. Each run is also
    written as episode records in OUT/records/, the data of the next round (efficienttrack round --data OUT/records).
    Rerun with the same settings to resume: the runs done are not repeated, a stopped run starts again (its earlier
    log kept as <reference>.stopped-1.jsonl).
    """
    from efficienttrack.data.references import load_references
    from efficienttrack.deploy.deployment import (
        DEPLOY_JSON,
        DEPLOY_OUTPUTS,
        deploy,
        deployed_tracking,
        machine_parts,
        policy_runtime,
        proven,
        record_shadow,
        recorded_verdict,
    )

    if not arm:
        raise EfficientTrackError(
            "deploy sends references to the machine: add --arm to allow motion "
            "(with --shadow the adjustment is only logged and the raw reference is sent; start there)"
        )
    check_output_folder(out)
    cfg = LoopConfig(hold_after=hold_after, stop_after=stop_after, stale_ticks=stale_ticks, stop_stale_ticks=stop_stale_ticks)
    references = load_references(refs)
    spec = _system_spec(system, plant, pd, system_opt, limits)
    make_machine, machine_limits, clock = machine_parts(spec, machine, parse_options(machine_opt, "--machine-opt"), fast)
    runtime = policy_runtime(policy, machine_limits, device)
    verdict = recorded_verdict(policy)
    if verdict is not None and not (shadow or accept_worse):
        raise EfficientTrackError(
            f"{policy}: {verdict}; its recorded evaluation tracked worse than PD, so it is not armed: run it with --shadow, "
            "or add --accept-worse to move the machine with it all the same"
        )
    if verdict is not None:
        typer.secho(f"warning: {policy}: {verdict}", fg=typer.colors.RED, err=True)
    if policy is not None and not shadow and not proven(policy):
        if not accept_worse:
            raise EfficientTrackError(
                f"{policy}: unproven: no evaluation and no shadow deployment of it is recorded, so it is not armed: run it "
                "with --shadow first (a run of every reference is then recorded with it), or evaluate it "
                "(efficienttrack evaluate --policy), or add --accept-worse to move the machine with it all the same"
            )
        typer.secho(f"warning: {policy}: unproven (never evaluated, never run in shadow mode)", fg=typer.colors.RED, err=True)
    _lock(ctx, out, resumable=False)  # the loop stops the machine and says what it wrote
    if force or not (out / DEPLOY_JSON).exists():  # an earlier deployment with the same settings resumes
        prepare_output_folder(out, DEPLOY_OUTPUTS, force)
    settings = {"policy": None if policy is None else str(policy), "machine": machine, "system": spec.to_dict(), "fast": fast}

    def report(result) -> None:
        s = result.summary()
        late = s.get("lateness_ms", {})
        typer.echo(
            f"{result.name}: {result.reason}, {result.ticks} ticks, lateness p99 {late.get('p99', 0):.2f} ms "
            f"max {late.get('max', 0):.2f} ms, overruns {s.get('overrun', 0)}, stale {s.get('stale', 0)}, "
            f"fallbacks {s.get('fallback', 0)}" + (f" ({result.error})" if result.error else "")
        )

    results = deploy(
        references, runtime, make_machine, machine_limits, out, cfg, clock, shadow, settings, report, between(between_episodes)
    )
    if not results:
        typer.echo(f"every run of {out} was done earlier; nothing was sent (--force starts afresh)")
        return
    if results[-1].stopped:
        typer.secho(f"stopped: {results[-1].name}: {results[-1].reason}; logs in {out}", fg=typer.colors.RED, err=True)
        raise typer.Exit(1)
    if shadow and policy is not None:  # every reference ran to its end: the policy has passed a shadow run
        facts = {"deployment": str(out.resolve()), "runs": len(references), "machine": machine or spec.system_name,
                 "when": datetime.now(UTC).isoformat(timespec="seconds")}  # fmt: skip
        try:
            record_shadow(policy, facts)
        except EfficientTrackError as exc:
            typer.secho(f"warning: the shadow run is not kept with the policy ({exc})", fg=typer.colors.RED, err=True)
    tracking = deployed_tracking(out)
    if tracking is not None:
        sent = "the raw reference (the controller alone)" if shadow else "the policy's references"
        typer.echo(
            f"tracking with {sent}: MAE {tracking['mae_deg']:.3f}°, RMSE {tracking['rmse_deg']:.3f}° over "
            f"{tracking['episodes']} record(s) (deploy.json; efficienttrack metrics {out / 'records'})"
        )
    earlier = len(references) - len(results)
    resumed = f" ({earlier} done earlier)" if earlier else ""
    typer.echo(f"{len(results)} run(s) done{resumed} ({'shadow' if shadow else 'armed'}); logs in {out}")

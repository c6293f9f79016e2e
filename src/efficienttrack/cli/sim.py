"""The ``sim`` commands: fit the hydraulic simulator to a machine's logs, and check how closely a simulator fits."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path
from typing import Annotated

import typer

from efficienttrack.cli.common import PdOpt, PlantOpt, RecursiveOpt, SystemOpt, SystemOpts, _lock, _system_spec
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import check_output_file, check_output_folder, finite_json, prepare_output_folder
from efficienttrack.systems.fit import FitConfig

sim_app = typer.Typer(help="The built-in hydraulic simulator: calibrate and check fidelity.", no_args_is_help=True)

SIM_VS_REAL_PREFIX = "sim_vs_real_"
"""Name prefix of the plots ``sim fidelity --plot`` draws."""

LogsOpt = Annotated[list[Path], typer.Option("--logs", help="Episode files or folders (logs with the PWM u; repeatable).")]

FIT = FitConfig()
"""The fit's default settings, shown as the ``sim calibrate`` options' defaults."""


def parse_ints(text: str, flag: str) -> tuple[int, ...]:
    """Parse a comma-separated list of integers given to an option, e.g. ``--delays 2,3,4``.

    Args:
        text: the option's value as given on the command line.
        flag: the option's name, used in error messages.

    Returns:
        The integers, in the order given.

    Raises:
        EfficientTrackError: an item is not an integer.
    """
    try:
        return tuple(int(item) for item in text.split(","))
    except ValueError as exc:
        raise EfficientTrackError(f"{flag} '{text}': expected comma-separated integers, e.g. 2,3,4") from exc


@sim_app.command("calibrate")
def sim_calibrate_command(
    ctx: typer.Context,
    logs: LogsOpt,
    out: Annotated[Path, typer.Option("--out", help="JSON preset to write (load it with --system-opt params_file=...).")],
    start: Annotated[Path | None, typer.Option("--start", help="Preset to start from (default: the shipped xe75).")] = None,
    delays: Annotated[
        str, typer.Option("--delays", help="Candidate transport delays, steps, comma-separated (e.g. 2,3,4).")
    ] = ",".join(map(str, FIT.delays)),
    max_windows: Annotated[int, typer.Option("--max-windows", help="Fit windows of each kind at most.")] = FIT.max_windows,
    max_nfev: Annotated[int, typer.Option("--max-nfev", help="Residual evaluations per least-squares stage.")] = FIT.max_nfev,
    max_ref_jitter: Annotated[
        float, typer.Option("--max-ref-jitter", help="Leave out episodes whose q_ref − q_des jitters more, rad.")
    ] = FIT.max_ref_jitter,
    recursive: RecursiveOpt = False,
) -> None:
    """Fit the hydraulic simulator to a machine's PD logs (PWM → motion) and write the preset."""
    from efficienttrack.systems.fit import calibrate, load_logs, save_params
    from efficienttrack.systems.hydraulic import HydraulicParams

    check_output_file(out)
    _lock(ctx, out, folder=False, resumable=False)  # two fits at once would replace each other's preset
    candidates = parse_ints(delays, "--delays")
    config = replace(FIT, delays=candidates, max_windows=max_windows, max_nfev=max_nfev, max_ref_jitter=max_ref_jitter)
    first = HydraulicParams.load(start) if start is not None else None
    result = calibrate(load_logs(logs, recursive=recursive), first, config, progress=typer.echo)
    save_params(result.params, out)
    typer.echo(
        f"open-loop window error (deg) {[round(float(v), 3) for v in result.open_loop_deg]}, closed-loop "
        f"{[round(float(v), 3) for v in result.closed_loop_deg]}; wrote {out}"
    )


@sim_app.command("fidelity")
def sim_fidelity_command(
    logs: LogsOpt,
    system: SystemOpt = None,
    plant: PlantOpt = None,
    pd: PdOpt = None,
    system_opt: SystemOpts = None,
    json_output: Annotated[bool, typer.Option("--json", help="Print one JSON line.")] = False,
    plot: Annotated[Path | None, typer.Option("--plot", help="Folder for sim-vs-real trace plots.")] = None,
    force: Annotated[
        bool, typer.Option("--force", help="Plot into a non-empty --plot folder: first delete its sim_vs_real_*.png.")
    ] = False,
    episodes: Annotated[int, typer.Option("--episodes", help="Episodes to plot.")] = 3,
    stride: Annotated[int, typer.Option("--stride", help="Steps between open-loop window starts.")] = 10,
    min_ref_jitter: Annotated[
        float, typer.Option("--min-ref-jitter", help="Leave out episodes whose q_ref − q_des jitters less, rad.")
    ] = 0.0,
    max_ref_jitter: Annotated[
        float | None, typer.Option("--max-ref-jitter", help="Leave out episodes whose q_ref − q_des jitters more, rad.")
    ] = None,
    recursive: RecursiveOpt = False,
) -> None:
    """Compare a simulator with real PD logs: closed-loop tracking MAE ratio, open-loop 20-step error and travel."""
    from efficienttrack.systems.fit import fidelity, load_logs, select_by_jitter
    from efficienttrack.workflow.plots import plot_sim_vs_real

    if plot is not None:
        check_output_folder(plot, "--plot")
    spec = _system_spec(system, plant, pd, system_opt)
    system_view, plant_view = spec.open(), spec.open_plant()
    records = load_logs(logs, need_u=plant_view is not None, recursive=recursive)
    if episodes < 0:
        raise EfficientTrackError(f"--episodes {episodes}: expected ≥ 0 episodes to plot")
    if min_ref_jitter != 0 or max_ref_jitter is not None:
        high = math.inf if max_ref_jitter is None else max_ref_jitter
        records = select_by_jitter(records, min_ref_jitter, high, option="--min-ref-jitter/--max-ref-jitter")
    if plot is not None:
        prepare_output_folder(plot, (f"{SIM_VS_REAL_PREFIX}*.png",), force, option="--plot")
    result = fidelity(records, system_view, plant_view, stride=stride)
    if plot is not None:
        for i in range(min(episodes, len(records))):
            n = len(records[i])
            name = records[i].meta.get("name", f"episode{i}")
            path = plot / f"{SIM_VS_REAL_PREFIX}{name}.png"
            plot_sim_vs_real(records[i].q, result.q_sim[:n, i], records[i].q_des, path, name)
    report = result.to_json()
    if json_output:
        typer.echo(json.dumps(finite_json(report, "sim fidelity"), allow_nan=False))
        return

    def fmt(values: list[float | None] | None, unit: str = "°") -> str:
        if values is None:
            return "n/a (no plant)"
        return ", ".join("n/a" if v is None else f"{v:.3f}{unit}" for v in values)

    typer.echo(f"{len(records)} episodes; joints boom, arm, bucket, swing")
    typer.echo(f"closed-loop PD MAE real:   {fmt(report['closed_loop']['real_mae_deg'])}")
    typer.echo(f"closed-loop PD MAE sim:    {fmt(report['closed_loop']['sim_mae_deg'])}")
    typer.echo(f"ratio sim/real:            {fmt(report['closed_loop']['ratio'], '')}")
    typer.echo(f"open-loop 20-step error:   {fmt(report['open_loop']['mpe20_deg'])}")
    typer.echo(f"open-loop travel real/sim: {fmt(report['open_loop']['travel_ratio20'], '')}")

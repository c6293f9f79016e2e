r"""A finished TD-MPC job scored with its planner instead of π's mean action, on the test and validation references.

A study's TD-MPC curve measures π's mean action, one network call a step; the public TD-MPC code evaluates with the
planner. This reads a finished job's folder (``curve.json``: loop, seed, budget, system, settings; ``model.pt``, read
with ``weights_only=True``), rebuilds the input pipeline from the study's training references less its validation
references (the split ``efficienttrack study`` makes), and runs the planner without exploration noise on every test
reference, then on every validation reference, as the study's recorder does (:func:`efficienttrack.envs.evaluate`,
:func:`efficienttrack.data.metrics.compute_metrics`). It prints π's figures at the job's final point beside the
planner's; with ``--json`` it also writes them.

Run (docs/tdmpc.md, "In the open loop"):
  for s in 0 1 2; do
    .venv/bin/python benchmarks/tdmpc_plan_eval.py runs/paper_open_tdmpc/jobs/tdmpc-open-s$s --system paper \
        --train-refs ../shared/data/references/train --test-refs ../shared/data/references/test
  done
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shlex
import sys
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch

from efficienttrack.baselines.tdmpc import TOLD, TDMPCSettings
from efficienttrack.baselines.tdmpc.train import evaluation_agent
from efficienttrack.core.fileio import write_json
from efficienttrack.core.progress import ProgressDisplay
from efficienttrack.core.settings import settings_from_dict
from efficienttrack.data.metrics import compute_metrics
from efficienttrack.data.references import load_references
from efficienttrack.envs import TrackingEnv, evaluate
from efficienttrack.envs.core import open_system
from efficienttrack.envs.features import learner_input
from efficienttrack.study.jobs import default_validation, split_validation
from efficienttrack.systems.spec import SystemSpec

SHOWN = ("mae_deg", "rmse_deg", "fmae_deg", "smt1_deg", "smt2_deg", "etd_mae_cm", "etd_fmae_cm")
"""The figures printed, in Table I's order."""


def read_job(folder: Path) -> dict[str, Any]:
    """The job's ``curve.json``, checked to be a finished TD-MPC run (a ``model.pt`` beside it)."""
    try:
        header = json.loads((folder / "curve.json").read_text())
    except (OSError, ValueError) as error:
        sys.exit(f"{folder}: no readable curve.json ({error})")
    if header.get("method") != "tdmpc" or not header.get("curve"):
        sys.exit(f"{folder}/curve.json: not a TD-MPC run with curve points")
    if not (folder / "model.pt").is_file():
        sys.exit(f"{folder}: no model.pt (the run has not finished)")
    return header


def counted(act: Callable[[np.ndarray], np.ndarray], tick: Callable[[], None]) -> Callable[[np.ndarray], np.ndarray]:
    """``act`` (observations (N, D) → actions (N, A)), calling ``tick`` after each call."""

    def act_and_tick(obs: np.ndarray) -> np.ndarray:
        action = act(obs)
        tick()
        return action

    return act_and_tick


def main() -> None:
    """Score the job's final model with the planner; print π's figures beside the planner's."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("job", type=Path, help="a finished TD-MPC job folder (OUT/jobs/tdmpc-<loop>-s<seed>)")
    parser.add_argument("--system", default="paper", help="built-in system the job ran on")
    parser.add_argument("--train-refs", type=Path, required=True, help="the study's training references")
    parser.add_argument("--test-refs", type=Path, required=True, help="the study's test references")
    parser.add_argument("--validation", type=int, default=None, help="references the study held out (default: its)")
    parser.add_argument("--json", type=Path, default=None, help="also write the figures to this file")
    args = parser.parse_args()
    print("$ " + " ".join(shlex.quote(a) for a in sys.argv))
    header = read_job(args.job)
    system = SystemSpec(system=args.system)
    if header["system"] != system.to_dict():
        sys.exit(f"--system {args.system}: the job ran on {header['system']}")
    settings = settings_from_dict(TDMPCSettings, header["settings"], f"{args.job}/curve.json: settings")
    settings = dataclasses.replace(settings, evaluate_with="plan", device="cpu")
    references = load_references(args.train_refs)
    count = default_validation(len(references)) if args.validation is None else args.validation
    train, validation = split_validation(references, count)
    test = load_references(args.test_refs)
    loop = header["loop"]
    torch.set_num_threads(1)
    see = learner_input(settings.inputs, loop, system, train)
    env = TrackingEnv(loop, system, train)
    obs_dim, action_dim = see(env.observation_space.sample()[None]).shape[1], env.action_space.shape[0]  # type: ignore[index]
    env.close()
    model = TOLD(obs_dim, action_dim, settings)
    model.load_state_dict(torch.load(args.job / "model.pt", map_location="cpu", weights_only=True))
    model.eval()
    machine = open_system(loop, system)
    final = max(header["curve"], key=lambda point: point["interaction_steps"])
    agent = evaluation_agent(model, settings, header["budget"], header["seed"], see)
    began = time.perf_counter()
    planned = {}
    with ProgressDisplay() as bar:  # the planner takes minutes: one tick per planned step of the batch
        for name, refs in (("test", test), ("validation", validation)):
            if refs:
                task = bar.add_task(f"planner, {len(refs)} {name} references (steps)", max(ref.steps for ref in refs))
                act = counted(agent, partial(bar.update, task, advance=1))
                planned[name] = compute_metrics(evaluate(act, refs, loop=loop, system=machine))
    wall = time.perf_counter() - began
    print(f"{args.job.name}: {loop} loop, seed {header['seed']}, {final['interaction_steps']:,} interaction steps; "
          f"the planner's evaluation took {wall:.0f} s")  # fmt: skip
    print("| agent | " + " | ".join(SHOWN) + " | validation MAE |")
    print("|---|" + "---:|" * (len(SHOWN) + 1))
    pi = [f"{final['metrics'][name]:.3f}" for name in SHOWN]
    pi_val = f"{final['validation']['mae_deg']:.3f}" if "validation" in final else "–"
    print("| π's mean action (the study's point) | " + " | ".join(pi) + f" | {pi_val} |")
    plan = [f"{planned['test'][name]:.3f}" for name in SHOWN]
    plan_val = f"{planned['validation']['mae_deg']:.3f}" if "validation" in planned else "–"
    print("| the planner, no exploration noise | " + " | ".join(plan) + f" | {plan_val} |")
    if args.json is not None:
        write_json(args.json, {"job": str(args.job), "interaction_steps": final["interaction_steps"],
                               "planner": planned, "wall_seconds": round(wall, 1)})  # fmt: skip


if __name__ == "__main__":
    main()

"""How steady the policy's training is through a model: the gradient norm and the loss, step by step.

The policy learns by backpropagating its loss through the frozen model over the rollout's h steps. Through a stiff
model (an accurate one of a stiff closed loop) the gradient over the whole rollout can explode: its norm spikes, the
clipped steps then point wherever the spikes point, and the loss climbs instead of falling. This trains the policy
as ``efficienttrack train-policy`` does (the ``cpu`` preset, ``--set`` changes it) and records the gradient norm of
every optimizer step before clipping; it prints, per tenth of the run, the norm's median, 90th percentile and largest
value and the loss's median and largest value, and, with ``--out``, writes both series to a ``.npy`` file (2, steps).

With ``--policy`` it trains nothing: from ``--windows`` recorded windows it rolls that policy through the model as the
training does and prints how the gradient of each window's loss with respect to its first reference spreads over the
windows (median, percentiles, the share of the sum carried by the top 1 %); the reference is moved by shifting the
first desired position, which the policy sees and the reference follows, with the rollout uncut and cut as the
settings say (``policy.truncate``, ``policy.row_cap``). A few windows carrying most of it is what an explosion looks
like.

Run (docs/comparison.md, "Exploding gradients through a better model"; the preset caps the gradient since
2026-11-29, ``--set policy.row_cap=0`` is the uncut rollout):
  R=runs/noise/paper/slow_s0
  .venv/bin/python benchmarks/policy_gradients.py --model $R/model.pt --data $R/records/train --steps 1000 \
      --set policy.row_cap=0
  .venv/bin/python benchmarks/policy_gradients.py --model runs/pol/paper/x10_s0/model.pt --data $R/records/train \
      --steps 1000 --set policy.row_cap=0       # and --set policy.truncate=5, or the cap; 2-4 min each on one thread
  .venv/bin/python benchmarks/policy_gradients.py --model runs/pol/paper/x10_s0/model.pt --data $R/records/train \
      --policy runs/noise/paper/slow_pol2x_s0/policy.pt --set policy.row_cap=0 --set policy.truncate=5    # seconds
"""

from __future__ import annotations

import argparse
from pathlib import Path
from unittest import mock

import numpy as np
import torch

from efficienttrack.core.fileio import atomic_write
from efficienttrack.data.dataset import Sequences
from efficienttrack.data.records import load_records
from efficienttrack.learn import policy as policy_module
from efficienttrack.learn.dynamics import ClosedLoopModel, load_model
from efficienttrack.learn.policy import (
    AdjustmentPolicy,
    desired_length,
    load_policy,
    policy_loss,
    policy_rollout,
    train_policy,
)
from efficienttrack.learn.settings import PolicyConfig
from efficienttrack.workflow.config import apply_overrides, preset


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=Path, required=True, help="model checkpoint (model.pt) to train through")
    parser.add_argument("--data", type=Path, required=True, help="folder of training episodes (read recursively)")
    parser.add_argument("--steps", type=int, default=1000, help="optimizer steps (default 1000)")
    parser.add_argument("--preset", default="cpu", help="settings preset (default cpu)")
    parser.add_argument("--set", action="append", default=[], dest="overrides", help="section.field=value (repeatable)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, help=".npy file for the (2, steps) gradient norms and losses")
    parser.add_argument("--policy", type=Path, help="a trained policy: the spread of the gradient over windows instead")
    parser.add_argument("--windows", type=int, default=1024, help="windows for --policy (default 1024)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(args.seed)
    cfg = apply_overrides(preset(args.preset), [*args.overrides, f"policy.steps={args.steps}"]).policy
    if args.policy is not None:
        spread(load_model(args.model), load_records(args.data, recursive=True), load_policy(args.policy), cfg, args.windows)
        return
    norms: list[float] = []
    clip = torch.nn.utils.clip_grad_norm_

    def recording_clip(parameters, max_norm, *rest, **options):
        norm = clip(parameters, max_norm, *rest, **options)
        norms.append(float(norm))
        return norm

    model, records = load_model(args.model), load_records(args.data, recursive=True)
    with mock.patch.object(policy_module.nn.utils, "clip_grad_norm_", recording_clip):  # the trainer's clip: the norm
        result = train_policy(cfg, model, records, device="cpu", seed=args.seed)
    series = np.stack([np.asarray(norms), result.losses])
    print(f"{args.model}, truncate {cfg.truncate}, row_cap {cfg.row_cap:g}, {result.steps} steps in {result.seconds:.0f} s")
    print("steps        grad norm: median     p90      max   loss: median      max")
    tenth = max(1, len(norms) // 10)
    for start in range(0, len(norms), tenth):
        norm, loss = series[:, start : start + tenth]
        print(f"{start:6d}+  {np.median(norm):18.3g} {np.percentile(norm, 90):8.3g} {norm.max():8.3g}"
              f"  {np.median(loss):13.3g} {loss.max():8.3g}")  # fmt: skip
    if args.out is not None:
        atomic_write(args.out, lambda f: np.save(f, series))


def spread(model: ClosedLoopModel, records: list, policy: AdjustmentPolicy, cfg: PolicyConfig, windows: int) -> None:
    """Print the spread over windows of ‖∂L/∂q^r_{t+1}‖, L a window's loss, uncut and cut as ``cfg`` says."""
    H = policy.cfg.rollout_length
    desired = desired_length(policy.cfg, H)
    data = Sequences(records, history=max(policy.cfg.history_length, model.cfg.history_length), future=desired)
    starts = data.starts(0)
    window = data.window(starts[torch.randperm(len(starts))[:windows]], horizon=0, desired=desired)
    model.requires_grad_(False)
    print(f"{len(window.obs_hist)} windows; ‖∂L/∂q^r_(t+1)‖ over them")
    cuts = [(0, 0.0)] + ([(cfg.truncate, cfg.row_cap)] if cfg.truncate or cfg.row_cap else [])
    for truncate, row_cap in cuts:
        shift = torch.zeros(len(window.obs_hist), 4, requires_grad=True)  # added to the first reference only
        q_star = torch.cat([window.qdes_future[:, :1] + shift[:, None], window.qdes_future[:, 1:]], 1)
        rolled = policy_rollout(model, policy, window.obs_hist, window.qref_hist, q_star, H, truncate, row_cap)
        L_track, L_reg = policy_loss(rolled.q_hat, rolled.a, window.qdes_future[:, :H], policy.cfg.gamma)
        (grad,) = torch.autograd.grad((L_track + policy.cfg.k_smooth * L_reg).sum(), shift)
        norm = np.sort(grad.norm(dim=1).numpy())
        top = norm[-max(1, len(norm) // 100) :].sum() / norm.sum()
        quantiles = ", ".join(f"{name} {np.percentile(norm, q):.3g}" for name, q in (("median", 50), ("p90", 90), ("p99", 99)))
        print(f"truncate {truncate}, row_cap {row_cap:g}: {quantiles}, largest {norm[-1]:.3g}; the top 1 % carry {top:.0%}")


if __name__ == "__main__":
    main()

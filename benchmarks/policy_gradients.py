"""How steady the policy's training is through a model: the gradient norm and the loss, step by step.

The policy learns by backpropagating its loss through the frozen model over the rollout's h steps. Through a stiff
model (an accurate one of a stiff closed loop) the gradient over the whole rollout can explode: its norm spikes, the
clipped steps then point wherever the spikes point, and the loss climbs instead of falling. This trains the policy
as ``efficienttrack train-policy`` does (the ``cpu`` preset, ``--set`` changes it) and records the gradient norm of
every optimizer step before clipping; it prints, per tenth of the run, the norm's median, 90th percentile and largest
value and the loss's median and largest value, and, with ``--out``, writes both series to a ``.npy`` file (2, steps).

Run (docs/comparison.md, "Truncated backpropagation"):
  R=runs/noise/paper/slow_s0
  .venv/bin/python benchmarks/policy_gradients.py --model $R/model.pt --data $R/records/train --steps 1000
  .venv/bin/python benchmarks/policy_gradients.py --model runs/pol/paper/x10_s0/model.pt --data $R/records/train \
      --steps 1000                                    # and --set policy.truncate=5; 2-4 min each on one thread
"""

from __future__ import annotations

import argparse
from pathlib import Path
from unittest import mock

import numpy as np
import torch

from efficienttrack.core.fileio import atomic_write
from efficienttrack.data.records import load_records
from efficienttrack.learn import policy as policy_module
from efficienttrack.learn.dynamics import load_model
from efficienttrack.learn.policy import train_policy
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
    args = parser.parse_args()
    torch.set_num_threads(1)
    cfg = apply_overrides(preset(args.preset), [*args.overrides, f"policy.steps={args.steps}"]).policy
    norms: list[float] = []
    clip = torch.nn.utils.clip_grad_norm_

    def recording_clip(parameters, max_norm, *rest, **options):
        norm = clip(parameters, max_norm, *rest, **options)
        norms.append(float(norm))
        return norm

    model, records = load_model(args.model), load_records(args.data, recursive=True)
    with mock.patch.object(policy_module.nn.utils, "clip_grad_norm_", recording_clip):  # the trainer's clip: the norm
        result = train_policy(cfg, model, records, device="cpu", seed=args.seed, progress=False)
    series = np.stack([np.asarray(norms), result.losses])
    print(f"{args.model}, truncate {cfg.truncate}, {result.steps} steps in {result.seconds:.0f} s")
    print("steps        grad norm: median     p90      max   loss: median      max")
    tenth = max(1, len(norms) // 10)
    for start in range(0, len(norms), tenth):
        norm, loss = series[:, start : start + tenth]
        print(f"{start:6d}+  {np.median(norm):18.3g} {np.percentile(norm, 90):8.3g} {norm.max():8.3g}"
              f"  {np.median(loss):13.3g} {loss.max():8.3g}")  # fmt: skip
    if args.out is not None:
        atomic_write(args.out, lambda f: np.save(f, series))


if __name__ == "__main__":
    main()

"""Wall time of the SB3 baselines at the ``full`` settings on one thread: 1,000 interaction steps, and 100,000 extrapolated.

Run: PYTHONPATH=src .venv/bin/python benchmarks/baseline_throughput.py [--steps 1000]
PPO (16 environments, SB3's 2048 steps per environment per rollout) does not update within 1,000 steps, so its
update is timed apart, on a 16 × 64-step rollout, per minibatch gradient step; the 100,000-step figure adds the 3
updates of 5,120 minibatches (10 epochs × 32,768 / 64) that 100,000 steps hold. SAC (one environment, 100 random steps,
then one gradient step of 256 per step) is timed over the steps after its warm-up. One evaluation (the deterministic
policy on 8 generated test cycles) is timed too: a curve measures one per evaluation point. The 100,000-step figures
are extrapolations from these measurements, not runs.
"""

import os

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[var] = "1"

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402
from stable_baselines3.common.callbacks import BaseCallback  # noqa: E402

from efficienttrack.baselines import SB3VecEnv, method_settings  # noqa: E402
from efficienttrack.data.cycles import generate_references  # noqa: E402
from efficienttrack.envs import TrackingVectorEnv, evaluate  # noqa: E402

TARGET = 100_000
"""The extrapolated budget, in interaction steps."""


def now() -> np.ndarray:
    """(wall, CPU) seconds: the CPU time of this one-thread process is what a step costs on an idle core."""
    return np.array([time.perf_counter(), time.process_time()])


class Clock(BaseCallback):
    """Stops learning at ``stop`` interaction steps and notes the (wall, CPU) time when ``mark`` was reached."""

    def __init__(self, mark: int, stop: int) -> None:
        super().__init__()
        self.mark, self.stop, self.marked = mark, stop, now()

    def _on_step(self) -> bool:
        if self.num_timesteps <= self.mark:
            self.marked = now()
        return self.num_timesteps < self.stop


def timed_learn(settings, refs, steps: int, mark: int = 0) -> tuple[np.ndarray, np.ndarray, object]:
    """((wall, CPU) s from ``mark`` to ``steps`` interaction steps, (wall, CPU) s in all, model) of ``settings`` learning."""
    model = settings.build(SB3VecEnv(TrackingVectorEnv(settings.n_envs, refs=refs)), seed=0)
    clock = Clock(mark, steps)
    start = now()
    model.learn(total_timesteps=steps, callback=clock)
    end = now()
    return end - (clock.marked if mark else start), end - start, model


def seconds(pair: np.ndarray) -> str:
    """``"12.3 s (CPU 4.5 s)"``."""
    return f"{pair[0]:.1f} s (CPU {pair[1]:.1f} s)"


def millis(pair: np.ndarray) -> str:
    """``"12.3 ms (CPU 4.5 ms)"``."""
    return f"{pair[0] * 1e3:.1f} ms (CPU {pair[1] * 1e3:.1f} ms)"


def minutes(pair: np.ndarray) -> str:
    """``"12.3 min (CPU 4.5 min)"``."""
    return f"{pair[0] / 60:.1f} min (CPU {pair[1] / 60:.1f} min)"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=1000, help="interaction steps timed per method")
    args = parser.parse_args()
    warm_up = method_settings("sac").learning_starts
    if args.steps <= warm_up:
        parser.error(f"--steps must exceed SAC's {warm_up} warm-up steps (the per-step time is measured after them)")
    torch.set_num_threads(1)
    refs = generate_references(16, seed=0)
    train, test = refs[:8], refs[8:]
    print(f"command: {' '.join([os.path.basename(sys.executable), *sys.argv])}  (torch threads 1, device cpu)")

    ppo = dataclasses.replace(method_settings("ppo"), device="cpu")
    collect, _, model = timed_learn(ppo, train, args.steps)
    small = dataclasses.replace(ppo, n_steps=64)  # one rollout of 16 × 64 = 1024 steps, its update, one more step
    rollout = small.n_envs * small.n_steps
    update, _, _ = timed_learn(small, train, rollout + 1, mark=rollout)
    per_minibatch = update / (small.n_epochs * rollout // small.batch_size)
    full_update = ppo.n_epochs * (ppo.n_envs * ppo.n_steps // ppo.batch_size) * per_minibatch
    updates = TARGET // (ppo.n_envs * ppo.n_steps)
    ppo_target = collect * TARGET / args.steps + updates * full_update
    start = now()
    evaluate(lambda obs: model.predict(obs, deterministic=True)[0], test)
    evaluation = now() - start

    sac = dataclasses.replace(method_settings("sac"), device="cpu")
    updating, sac_total, _ = timed_learn(sac, train, args.steps, mark=sac.learning_starts)
    per_step = updating / (args.steps - sac.learning_starts)
    sac_target = sac_total - updating + per_step * (TARGET - sac.learning_starts)

    print(f"PPO, 16 environments: {args.steps:,} steps (measured, collection only): {seconds(collect)}")
    print(f"  one minibatch of {ppo.batch_size} (measured): {millis(per_minibatch)}")
    print(f"  one update at the full settings, 10 x 32,768 / 64 minibatches (extrapolated): {seconds(full_update)}")
    print(f"  {TARGET:,} steps, {updates} updates (extrapolated): {minutes(ppo_target)}")
    print(f"SAC, 1 environment: {args.steps:,} steps (measured): {seconds(sac_total)}")
    print(f"  per step after the warm-up, with its gradient step (measured): {millis(per_step)}")
    print(f"  {TARGET:,} steps (extrapolated): {minutes(sac_target)}")
    print(
        f"one evaluation on {len(test)} test cycles ({sum(len(r) - 1 for r in test):,} steps, measured): {seconds(evaluation)}"
    )


if __name__ == "__main__":
    main()

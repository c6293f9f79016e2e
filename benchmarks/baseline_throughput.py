"""Wall and CPU time of the SB3 baselines on one thread: PPO at its cpu settings, SAC at candidate settings.

Run: PYTHONPATH=src .venv/bin/python benchmarks/baseline_throughput.py [--steps 1000] [--system paper]
PPO (16 environments, SB3's 2048 steps per environment per rollout) does not update within 1,000 steps, so its
update is timed apart, on a 16 × 64-step rollout, per minibatch gradient step; the 100,000-step figure adds the 3
updates of 5,120 minibatches (10 epochs × 32,768 / 64) that 100,000 steps hold. SAC is timed at each setting of
``SAC_CANDIDATES`` (changes to the ``cpu`` preset: parallel environments, gradient steps, batch, network), over the
interaction steps after its 100 random warm-up steps, and extrapolated to the paper's 442,892 steps: its cost is its
gradient steps, so one gradient step per k interaction steps costs about a k-th. One evaluation (the deterministic
policy on 8 generated test cycles) is timed too: a curve measures one per evaluation point. Every environment step
goes through the shared observation pipeline, as in training. The extrapolated figures are not runs.
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
from efficienttrack.baselines.vec_env import FeatureVecEnv  # noqa: E402
from efficienttrack.data.cycles import generate_references  # noqa: E402
from efficienttrack.envs import TrackingVectorEnv, evaluate  # noqa: E402
from efficienttrack.envs.features import learner_input  # noqa: E402
from efficienttrack.systems.spec import SystemSpec  # noqa: E402

TARGET = 100_000
"""PPO's extrapolated budget, in interaction steps."""
SAC_TARGET = 442_892
"""SAC's extrapolated budget: the paper's closed-loop SAC row (Table I)."""
SAC_CANDIDATES: dict[str, dict[str, object]] = {
    "1 env, 1 step of 256 per step, (256, 256) [cpu until 2026-11-26]": {"n_envs": 1},
    "2 envs, 1 step of 256 per 2 steps, (256, 256)": {"n_envs": 2},
    "4 envs, 1 step of 256 per 4 steps, (256, 256) [cpu]": {"n_envs": 4},
    "8 envs, 1 step of 512 per 8 steps, (256, 256)": {"n_envs": 8, "batch_size": 512},
    "16 envs, 1 step of 256 per 16 steps, (512, 512, 512, 128)": {"n_envs": 16, "net_arch": (512, 512, 512, 128)},
}
"""SAC settings timed: changes to the ``cpu`` preset (its batch 256 and (256, 256) networks unless named)."""


def now() -> np.ndarray:
    """(wall, CPU) seconds: the CPU time of this one-thread process is what a step costs on an idle core."""
    return np.array([time.perf_counter(), time.process_time()])


class Clock(BaseCallback):
    """Stops learning at ``stop`` interaction steps; notes the count and (wall, CPU) time of the last step ≤ ``mark``."""

    def __init__(self, mark: int, stop: int) -> None:
        super().__init__()
        self.mark, self.stop, self.marked, self.marked_at = mark, stop, now(), 0

    def _on_step(self) -> bool:
        if self.num_timesteps <= self.mark:
            self.marked, self.marked_at = now(), self.num_timesteps
        return self.num_timesteps < self.stop


def timed_learn(settings, system, refs, steps: int, mark: int = 0) -> tuple[np.ndarray, int, np.ndarray, object]:
    """((wall, CPU) s after ``mark``, interaction steps after it, (wall, CPU) s in all, model) of ``settings`` learning."""
    env = SB3VecEnv(TrackingVectorEnv(settings.n_envs, system=system, refs=refs))
    see = learner_input(settings.inputs, "closed", system, refs)
    model = settings.build(env if settings.inputs == "raw" else FeatureVecEnv(env, see), seed=0)
    clock = Clock(mark, steps)
    start = now()
    model.learn(total_timesteps=steps, callback=clock)
    end = now()
    return end - (clock.marked if mark else start), model.num_timesteps - clock.marked_at, end - start, model


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
    parser.add_argument("--steps", type=int, default=1000, help="interaction steps timed per method and SAC setting")
    parser.add_argument("--system", default="xe75", help="built-in system: xe75 or paper (the paper's simulator)")
    args = parser.parse_args()
    warm_up = method_settings("sac").learning_starts
    if args.steps <= warm_up:
        parser.error(f"--steps must exceed SAC's {warm_up} warm-up steps (the per-step time is measured after them)")
    torch.set_num_threads(1)
    system = SystemSpec(system=args.system)
    refs = generate_references(16, seed=0)
    train, test = refs[:8], refs[8:]
    print(f"command: {' '.join([os.path.basename(sys.executable), *sys.argv])}  (torch threads 1, device cpu)")
    print(f"system {args.system}, load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs at the start")

    ppo = dataclasses.replace(method_settings("ppo"), device="cpu")
    collect, _, _, model = timed_learn(ppo, system, train, args.steps)
    small = dataclasses.replace(ppo, n_steps=64)  # one rollout of 16 × 64 = 1024 steps, its update, one more step
    rollout = small.n_envs * small.n_steps
    update, _, _, _ = timed_learn(small, system, train, rollout + 1, mark=rollout)
    per_minibatch = update / (small.n_epochs * rollout // small.batch_size)
    full_update = ppo.n_epochs * (ppo.n_envs * ppo.n_steps // ppo.batch_size) * per_minibatch
    updates = TARGET // (ppo.n_envs * ppo.n_steps)
    ppo_target = collect * TARGET / args.steps + updates * full_update
    see = learner_input(ppo.inputs, "closed", system, train)
    start = now()
    evaluate(lambda obs: model.predict(see(obs), deterministic=True)[0], test, "closed", system)
    evaluation = now() - start
    print(f"PPO, 16 environments: {args.steps:,} steps (measured, collection only): {seconds(collect)}")
    print(f"  one minibatch of {ppo.batch_size} (measured): {millis(per_minibatch)}")
    print(f"  one update at the full settings, 10 x 32,768 / 64 minibatches (extrapolated): {seconds(full_update)}")
    print(f"  {TARGET:,} steps, {updates} updates (extrapolated): {minutes(ppo_target)}")
    print(
        f"one evaluation on {len(test)} test cycles ({sum(len(r) - 1 for r in test):,} steps, measured): {seconds(evaluation)}"
    )

    print(f"SAC, per interaction step after the warm-up (measured), and {SAC_TARGET:,} steps (extrapolated):")
    for name, change in SAC_CANDIDATES.items():
        sac = dataclasses.replace(method_settings("sac"), device="cpu", **change)
        updating, timed, total, _ = timed_learn(sac, system, train, args.steps, mark=sac.learning_starts)
        per_step = updating / timed
        target = total - updating + per_step * (SAC_TARGET - sac.learning_starts)
        print(f"  {name}: {millis(per_step)} per step; {minutes(target)}")


if __name__ == "__main__":
    main()

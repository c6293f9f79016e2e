"""Wall and CPU time of TD-MPC on one thread, per interaction step after the seeding, extrapolated.

Run: PYTHONPATH=src .venv/bin/python benchmarks/tdmpc_throughput.py [--steps 1000] [--preset paper] [--system paper]
The seeding phase (``seed_steps`` random steps into the replay buffer; 5,000 at ``paper``) is run and timed; then
``--steps`` steps of what every later step does (plan over the horizon of the schedule's end, step the machine, store,
one update of one batch over ``horizon`` steps; at ``paper``: 6 × (512 + 25) sequences, batch 512) are timed, planning
and update apart. One evaluation is timed with π's mean action (the default) and one planned step for the 8 test cycles
at once (``evaluate_with="plan"``). The figures for 1,000 steps (when fewer are timed), EfficientTrack's one pass on
the paper's simulator (17,672), 100,000 and the paper's 197,890 steps (the burst of ``seed_steps`` updates when the
seeding ends included) are extrapolations from these measurements, not runs.
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

from efficienttrack.baselines.tdmpc import TOLD, Learner, PrioritizedBuffer, plan, tdmpc_settings  # noqa: E402
from efficienttrack.baselines.tdmpc.train import evaluation_agent, planner_config  # noqa: E402
from efficienttrack.data.cycles import generate_references  # noqa: E402
from efficienttrack.envs import TrackingEnv, evaluate  # noqa: E402
from efficienttrack.envs.features import learner_input  # noqa: E402
from efficienttrack.systems.spec import SystemSpec  # noqa: E402

TARGETS = (1_000, 17_672, 100_000, 197_890)
"""The extrapolated budgets, in interaction steps (17,672: EfficientTrack's one pass on the paper's simulator; 197,890:
the paper's TD-MPC I.S., closed loop)."""


def now() -> np.ndarray:
    """(wall, CPU) seconds: the CPU time of this one-thread process is what a step costs on an idle core."""
    return np.array([time.perf_counter(), time.process_time()])


def fmt(pair: np.ndarray, unit: str = "s") -> str:
    """``"12.3 s (CPU 4.5 s)"`` in s, ms, min or h."""
    scale = {"ms": 1e3, "s": 1.0, "min": 1 / 60, "h": 1 / 3600}[unit]
    return f"{pair[0] * scale:.1f} {unit} (CPU {pair[1] * scale:.1f} {unit})"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=1000, help="interaction steps timed after the seeding")
    parser.add_argument("--preset", default="paper", help="TD-MPC preset: paper, cpu (TD-MPC (reduced)) or tiny")
    parser.add_argument("--system", default=None, help="built-in system (e.g. paper); default: the built-in xe75")
    args = parser.parse_args()
    torch.set_num_threads(1)
    settings = dataclasses.replace(tdmpc_settings(args.preset), device="cpu")
    system = SystemSpec() if args.system is None else SystemSpec(system=args.system)
    refs = generate_references(16, seed=0)
    train, test = refs[:8], refs[8:]
    print(f"command: {' '.join([os.path.basename(sys.executable), *sys.argv])}  (torch threads 1, device cpu)")
    print(f"load average at the start: {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")

    env = TrackingEnv("closed", system, train)
    see = learner_input(settings.inputs, "closed", system, train)
    obs_dim, action_dim = see(env.observation_space.sample()[None]).shape[1], env.action_space.shape[0]
    rng, generator = np.random.default_rng(0), torch.Generator().manual_seed(0)
    torch.manual_seed(0)
    model = TOLD(obs_dim, action_dim, settings)
    learner = Learner(model, settings, generator)
    buffer = PrioritizedBuffer(settings.buffer_size, obs_dim, action_dim, settings.horizon, settings.per_alpha, 0.4)
    raw = env.reset(seed=0)[0]
    obs, first = see(raw[None])[0], True

    def step(action: np.ndarray) -> None:
        nonlocal raw, obs, first
        raw_next, reward, _, truncated, _ = env.step(action)
        next_obs = see(raw_next[None])[0]
        buffer.add(obs, action, reward, next_obs, first)
        first = truncated
        raw = env.reset()[0] if truncated else raw_next
        obs = see(raw[None])[0] if truncated else next_obs

    start = now()
    for _ in range(settings.seed_steps):
        step(rng.uniform(-1, 1, action_dim).astype(np.float32))
    seeding = now() - start

    config = planner_config(settings, settings.schedule_steps, action_dim)  # the schedules' end: the final horizon
    planning, updating, warm = np.zeros(2), np.zeros(2), None
    for _ in range(args.steps):
        start = now()
        with torch.no_grad():
            z = model.encode(torch.as_tensor(obs)[None])
        result = plan(model, z, config, generator, None if first else warm, explore=True)
        warm = result.mean
        step(result.action[0].numpy())
        middle = now()
        batch = buffer.sample(settings.batch_size, rng)
        _, priority = learner.update(batch)
        buffer.update(batch.index, priority.numpy())
        updating += now() - middle
        planning += middle - start
    per_plan, per_update = planning / args.steps, updating / args.steps
    per_step = per_plan + per_update

    start = now()
    evaluate(evaluation_agent(model, settings, settings.schedule_steps, 0, see), test, "closed", system)
    policy_evaluation = now() - start
    plan_settings = dataclasses.replace(settings, evaluate_with="plan")
    planned = evaluation_agent(model, plan_settings, settings.schedule_steps, 0, see)
    batch_obs = np.repeat(raw[None], len(test), axis=0)
    start = now()
    planned(batch_obs)
    planned_step = now() - start
    test_steps = sum(len(r) - 1 for r in test)

    print(f"seeding, {settings.seed_steps:,} random steps into the buffer (measured): {fmt(seeding)}")
    print(f"{args.steps:,} steps after the seeding (measured): {fmt(planning + updating)}")
    print(f"  per step: planning (with the machine's step) {fmt(per_plan, 'ms')}, update {fmt(per_update, 'ms')}")
    print(f"  {TARGETS[0]:,} steps after the seeding (extrapolated): {fmt(per_step * TARGETS[0], 'min')}")
    for target in TARGETS[1:]:
        total = seeding + settings.seed_steps * per_update + (target - settings.seed_steps) * per_step
        print(f"  {target:,} steps, seeding and its {settings.seed_steps:,}-update burst included (extrapolated): ", end="")
        print(fmt(total, "h"))
    print(f"one evaluation with pi on {len(test)} test cycles ({test_steps:,} steps, measured): {fmt(policy_evaluation)}")
    print(f"one planned step for {len(test)} machines at once (measured): {fmt(planned_step, 'ms')}")
    longest = max(len(r) for r in test) - 1
    print(f"  one evaluation with the planner, {longest} steps of all 8 at once (extrapolated): ", end="")
    print(fmt(planned_step * longest, "min"))


if __name__ == "__main__":
    main()

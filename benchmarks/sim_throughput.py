"""Throughput of the built-in hydraulic simulator on one core: env-steps/s of the plant and of the PD closed loop.

Run: .venv/bin/python benchmarks/sim_throughput.py [--seconds S]
Targets: plant ≥ 1,000,000 and closed loop ≥ 500,000 env-steps/s at N = 4096; ≥ 20,000 at N = 1.
Time is the process's CPU time (one thread), so the figures hold on a machine shared with other jobs.
"""

import os

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[var] = "1"

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from efficienttrack.systems.hydraulic import xe75_closed_loop, xe75_plant  # noqa: E402


def steps_per_second(system, inputs: np.ndarray, seconds: float) -> float:
    """Env-steps/s (machine-steps) of ``system.step`` cycling through ``inputs`` (K, N, 4) for about ``seconds``."""
    n = inputs.shape[1]
    system.reset(np.zeros((n, 4)) if n > 1 else np.zeros(4))
    batch = inputs if n > 1 else inputs[:, 0]
    system.step(batch[0])
    steps, start = 0, time.process_time()
    while (elapsed := time.process_time() - start) < seconds:
        for x in batch:
            system.step(x)
        steps += len(batch)
    return steps * n / elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=1.5, help="measuring time per row")
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    print(f"command: {' '.join([os.path.basename(sys.executable), *sys.argv])}  (1 thread, CPU time)")
    print(f"{'N':>6} | {'plant steps/s':>14} | {'closed loop steps/s':>20}")
    for n in (1, 64, 4096):
        pwm = rng.uniform(-1000, 1000, (50, n, 4))
        q_ref = rng.uniform(-0.3, 0.3, (50, n, 4))
        plant = steps_per_second(xe75_plant(), pwm, args.seconds)
        closed = steps_per_second(xe75_closed_loop(), q_ref, args.seconds)
        print(f"{n:>6} | {plant:>14,.0f} | {closed:>20,.0f}")


if __name__ == "__main__":
    main()

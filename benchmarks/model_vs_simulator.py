"""What a closed-loop model teaches the policy, against the simulator it stands for.

The policy is trained by backpropagating its loss through the frozen model, so what it learns from is not the model's
prediction error but (a) the model's response to a change of reference, ∂q̂_{t+k}/∂q^r_{t+1}, and (b) the model's
judgement of the loss of a policy. A model can predict recorded runs well and still get either wrong. On a deterministic
simulator both can be measured:

1. **Response.** Replay each recorded episode in the simulator, change one reference q^r_{t+1} by ±ε on one joint at a
   time from every ``--stride``-th step, and take central differences of the positions over the next ``--horizon``
   steps, in the simulator and in each model (rolled from the recorded histories, as the policy's training rolls it).
   Printed per model: its MPE on the replays (°, as ``efficienttrack model-error``); the response error
   ‖J_model − J_sim‖ / ‖J_sim‖ over all starts and joints, overall and k steps ahead, J[k] the (4 × 4) change of
   q_{t+k} per change of q^r_{t+1}; and the cosine between the model's and the simulator's ∂L_track/∂q^r_{t+1}.
2. **Judgement** (with ``--policy``). From the same starts, run each policy for ``--horizon`` steps in the simulator
   (replaying the record up to the start) and in each model, and print the policy's loss terms on those windows
   (:func:`efficienttrack.learn.policy.policy_loss`: L_track, L_reg, and the 20-step MAE) as each judge sees them.
   A model teaches the policy well when it ranks the policies as the simulator does.

Run (docs/comparison.md, "Training length: steps or epochs"):
  P=runs/paper_et_closed/jobs/efficienttrack-closed-s0/passes_10
  .venv/bin/python benchmarks/model_vs_simulator.py --system paper --records $P/records/train --every-record 10 \
      --model cpu=$P/model.pt --model x10=runs/paper_epochs/p10_x10/model.pt \
      --policy cpu=$P/policy.pt --policy x10=runs/paper_epochs/x10model_pol1x/policy.pt
"""

from __future__ import annotations

import argparse
import shlex
import sys
from collections import defaultdict

import numpy as np
import torch

from efficienttrack.core.angles import wrap
from efficienttrack.data.records import EpisodeRecord, load_records
from efficienttrack.learn.dynamics import ClosedLoopModel, load_model, rollout
from efficienttrack.learn.policy import AdjustmentPolicy, load_policy, policy_loss, policy_rollout
from efficienttrack.systems.spec import load_system


def model_time_references(record: EpisodeRecord, refs: np.ndarray) -> np.ndarray:
    """References in the model's time, ``q^r_0 = q_0`` and ``q^r_{t+1} = refs[:, t]``.

    Args:
        record: the episode (its first position).
        refs: (N, T, 4) rad, the references sent at each step.

    Returns:
        (N, T + 1, 4) rad.
    """
    return np.concatenate([np.broadcast_to(record.q[0], (len(refs), 1, 4)), refs], axis=1)


def perturbed_references(q_ref: np.ndarray, starts: np.ndarray, eps: float) -> np.ndarray:
    """The record's references unchanged, then with q_ref[s] ± ε on each joint, for every start s.

    Args:
        q_ref: (T, 4) rad, the references sent at each step.
        starts: (S,) int, the steps s whose reference is changed.
        eps: the change, rad.

    Returns:
        (1 + 8S, T, 4) rad: the unchanged references, then for each start +ε and −ε on joints 0…3 in turn.
    """
    n = len(starts)
    refs = np.repeat(q_ref[None], 1 + 8 * n, axis=0)
    refs[1 + np.arange(8 * n), np.repeat(starts, 8), np.tile(np.repeat(np.arange(4), 2), n)] += np.tile([eps, -eps], 4 * n)
    return refs


def replay(system_spec: str, record: EpisodeRecord, refs: np.ndarray) -> np.ndarray:
    """Run the simulator from the record's start under each batch of references.

    Args:
        system_spec: a reference-level system (``load_system``).
        record: the episode (its first position is the start).
        refs: (N, T, 4) rad, the references sent at each step.

    Returns:
        (N, T, 8) [rad, rad/s], the observations o_0 … o_{T−1}.
    """
    system = load_system(system_spec)
    obs = [system.reset(np.repeat(record.q[:1], len(refs), axis=0))]
    for t in range(refs.shape[1] - 1):
        obs.append(system.step(refs[:, t]))
    return np.stack(obs, axis=1)


def responses(runs: np.ndarray, eps: float) -> np.ndarray:
    """Central differences of each start's ± runs.

    Args:
        runs: (S, 8, H, 4) rad, each start's ± runs (in :func:`perturbed_references`'s order), q_{s+1} … q_{s+H}.
        eps: rad.

    Returns:
        (S, H, 4, 4): [start, k, joint moved, joint changed], the change of q_{s+k} per unit change of q^r_{s+1}.
    """
    pairs = runs.reshape(len(runs), 4, 2, *runs.shape[2:])
    return np.transpose(wrap(pairs[:, :, 0] - pairs[:, :, 1]) / (2 * eps), (0, 2, 3, 1))


def own_runs(starts: np.ndarray) -> np.ndarray:
    """(S, 8) int: the batches of :func:`perturbed_references` that change each start's reference."""
    return 1 + 8 * np.arange(len(starts))[:, None] + np.arange(8)


@torch.inference_mode()
def model_positions(
    model: ClosedLoopModel, obs: np.ndarray, q_ref: np.ndarray, starts: np.ndarray, horizon: int
) -> np.ndarray:
    """Roll the model from each start's recorded history under every batch of references.

    Args:
        model: g_θ.
        obs: (T, 8), the unchanged run's observations.
        q_ref: (N, T + 1, 4) rad, :func:`model_time_references` of each batch.
        starts: (S,) int, each ≥ the model's history − 1.
        horizon: H.

    Returns:
        (N, S, H, 4) rad: for each batch and each start s, the predicted q_{s+1} … q_{s+H}.
    """
    h = model.cfg.history_length
    n, s = len(q_ref), len(starts)
    hist = starts[:, None] + np.arange(-h + 1, 1)
    ahead = starts[:, None] + np.arange(1, horizon + 1)
    obs_hist = torch.as_tensor(obs[hist], dtype=torch.float32).expand(n, s, h, 8).reshape(n * s, h, 8)
    qref_hist = torch.as_tensor(q_ref[:, hist], dtype=torch.float32).reshape(n * s, h, 4)
    qref_future = torch.as_tensor(q_ref[:, ahead], dtype=torch.float32).reshape(n * s, horizon, 4)
    return rollout(model, obs_hist, qref_hist, qref_future)[..., :4].reshape(n, s, horizon, 4).double().numpy()


def loss_gradient(jacobian: np.ndarray, q: np.ndarray, q_star: np.ndarray, gamma: float) -> np.ndarray:
    """∂L_track/∂q^r_{s+1} of L_track ∝ Σ_k γ^k ‖q_{s+k} − q*_{s+k}‖², up to a constant factor.

    Args:
        jacobian: (S, H, 4, 4), :func:`responses`.
        q: (S, H, 4) rad, the unchanged run's positions.
        q_star: (S, H, 4) rad, the desired positions.
        gamma: γ.

    Returns:
        (S, 4).
    """
    weights = gamma ** np.arange(1, jacobian.shape[1] + 1)
    return np.einsum("k,skij,ski->sj", weights, jacobian, wrap(q - q_star))


def desired_ahead(record: EpisodeRecord, steps: np.ndarray) -> np.ndarray:
    """q*_{t} for the model-time steps t (``q*_{t+1} = q_des[t]``), the last one repeated past the end: same shape + (4,)."""
    return record.q_des[np.minimum(steps - 1, len(record) - 1)]


@torch.inference_mode()
def policy_in_simulator(
    system_spec: str, record: EpisodeRecord, policy: AdjustmentPolicy, starts: np.ndarray, horizon: int
) -> tuple[np.ndarray, np.ndarray]:
    """Replay the record up to each start, then let the policy adjust the references for ``horizon`` steps.

    One simulated machine per start, all batched; the loop is over time only.

    Args:
        system_spec: a reference-level system.
        record: the episode.
        policy: π_φ.
        starts: (S,) int, each ≥ the policy's history − 1.
        horizon: H.

    Returns:
        (S, H, 4) rad positions q_{s+1} … q_{s+H} and (S, H, 4) rad the actions a_s … a_{s+H−1}.
    """
    h, f = policy.cfg.history_length, policy.cfg.future_length
    system = load_system(system_spec)
    n, steps = len(starts), int(starts.max()) + horizon
    obs = np.zeros((n, steps + 1, 8))
    q_ref = np.zeros((n, steps + 1, 4))
    obs[:, 0], q_ref[:, 0] = system.reset(np.repeat(record.q[:1], n, axis=0)), record.q[0]
    actions = np.zeros((n, horizon, 4))
    for t in range(steps):
        sent = np.repeat(record.q_ref[min(t, len(record) - 1)][None], n, axis=0)
        acting = np.flatnonzero((starts <= t) & (t < starts + horizon))
        if len(acting):
            window = np.arange(t - h + 1, t + 1)
            future = torch.as_tensor(desired_ahead(record, t + 1 + np.arange(f)), dtype=torch.float32)
            obs_hist = torch.as_tensor(obs[acting][:, window], dtype=torch.float32)
            qref_hist = torch.as_tensor(q_ref[acting][:, window], dtype=torch.float32)
            a = policy(obs_hist, qref_hist, future.expand(len(acting), f, 4)).double().numpy()
            sent[acting] = desired_ahead(record, np.array(t + 1)) + a
            actions[acting, t - starts[acting]] = a
        q_ref[:, t + 1] = sent
        obs[:, t + 1] = system.step(sent)
    ahead = starts[:, None] + np.arange(1, horizon + 1)
    return obs[np.arange(n)[:, None], ahead, :4], actions


@torch.inference_mode()
def policy_in_model(
    model: ClosedLoopModel,
    policy: AdjustmentPolicy,
    obs: np.ndarray,
    q_ref: np.ndarray,
    record: EpisodeRecord,
    starts: np.ndarray,
    horizon: int,
) -> tuple[np.ndarray, np.ndarray]:
    """The same windows in the model, from the recorded histories (as the policy's training rolls them).

    Args:
        model: g_θ.
        policy: π_φ.
        obs: (T, 8), the recorded run's observations.
        q_ref: (T + 1, 4) rad, its references in model time.
        record: the episode (desired positions).
        starts: (S,) int, each ≥ both networks' history − 1.
        horizon: H.

    Returns:
        (S, H, 4) rad predicted positions and (S, H, 4) rad actions.
    """
    h = max(policy.cfg.history_length, model.cfg.history_length)
    hist = starts[:, None] + np.arange(-h + 1, 1)
    future = desired_ahead(record, starts[:, None] + 1 + np.arange(horizon + policy.cfg.future_length))
    obs_hist = torch.as_tensor(obs[hist], dtype=torch.float32)
    qref_hist = torch.as_tensor(q_ref[hist], dtype=torch.float32)
    rolled = policy_rollout(model, policy, obs_hist, qref_hist, torch.as_tensor(future, dtype=torch.float32), horizon)
    return rolled.q_hat.double().numpy(), rolled.a.double().numpy()


def loss_terms(q: np.ndarray, a: np.ndarray, q_star: np.ndarray, gamma: float) -> np.ndarray:
    """(S, 3): each window's L_track, L_reg (rad²) and mean |error| (rad), the policy's loss terms."""
    l_track, l_reg = policy_loss(torch.as_tensor(q), torch.as_tensor(a), torch.as_tensor(q_star), gamma)
    return np.stack([l_track.numpy(), l_reg.numpy(), np.abs(wrap(q - q_star)).mean((1, 2))], axis=1)


def named_path(text: str) -> tuple[str, str]:
    """A ``NAME=PATH`` option as (name, path)."""
    name, sep, path = text.partition("=")
    if not (name and sep and path):
        raise argparse.ArgumentTypeError(f"{text!r}: expected NAME=PATH")
    return name, path


def main() -> None:
    """Print each model's prediction and response error against the simulator, then how each judge sees each policy."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--system", default="paper", help="reference-level simulator (default paper)")
    parser.add_argument("--records", required=True, help="folder of recorded episodes to replay (subfolders too)")
    parser.add_argument("--every-record", type=int, default=1, help="use every N-th record")
    parser.add_argument(
        "--model", type=named_path, action="append", required=True, help="NAME=PATH of a closed-loop model (repeatable)"
    )
    parser.add_argument("--policy", type=named_path, action="append", default=[], help="NAME=PATH of a policy to judge")
    parser.add_argument("--horizon", type=int, default=20)
    parser.add_argument("--stride", type=int, default=10, help="a start every N steps")
    parser.add_argument("--eps-deg", type=float, default=0.5, help="the change of one reference, degrees")
    parser.add_argument("--gamma", type=float, default=0.98)
    args = parser.parse_args()
    print("$ " + " ".join(shlex.quote(a) for a in sys.argv))
    torch.set_num_threads(1)
    models = {name: load_model(path) for name, path in args.model}
    policies = {name: load_policy(path) for name, path in args.policy}
    h = max(net.cfg.history_length for net in [*models.values(), *policies.values()])
    eps, horizon = np.deg2rad(args.eps_deg), args.horizon
    records = load_records(args.records, recursive=True)[:: args.every_record]
    sim, positions, desired, predicted = [], [], [], defaultdict(list)
    judged = defaultdict(list)
    for i, record in enumerate(records, 1):
        print(f"record {i}/{len(records)}", file=sys.stderr, flush=True)
        starts = np.arange(h - 1, len(record) - horizon, args.stride)
        ahead = starts[:, None] + np.arange(1, horizon + 1)
        refs = perturbed_references(record.q_ref, starts, eps)
        obs = replay(args.system, record, refs)
        q_ref = model_time_references(record, refs)
        sim.append(responses(obs[own_runs(starts)[:, :, None], ahead[:, None], :4], eps))
        positions.append(obs[0, ahead, :4])
        desired.append(desired_ahead(record, ahead))
        for name, model in models.items():
            q_hat = model_positions(model, obs[0], q_ref, starts, horizon)
            predicted[name].append((q_hat[0], responses(q_hat[own_runs(starts), np.arange(len(starts))[:, None]], eps)))
        for policy_name, policy in policies.items():
            judged["simulator", policy_name].append(
                loss_terms(*policy_in_simulator(args.system, record, policy, starts, horizon), desired[-1], args.gamma)
            )
            for name, model in models.items():
                rolled = policy_in_model(model, policy, obs[0], q_ref[0], record, starts, horizon)
                judged[name, policy_name].append(loss_terms(*rolled, desired[-1], args.gamma))
    j_sim, q_sim, q_star = np.concatenate(sim), np.concatenate(positions), np.concatenate(desired)
    grad_sim = loss_gradient(j_sim, q_sim, q_star, args.gamma)
    print(f"{len(records)} records, {len(j_sim)} starts, ε = {args.eps_deg}°, H = {horizon}\n")
    print("| model | MPE (°) | response error | k=1 | k=5 | k=10 | k=20 | ∂L_track/∂q^r cosine, median | mean |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for name in models:
        q_hat = np.concatenate([p[0] for p in predicted[name]])
        j_hat = np.concatenate([p[1] for p in predicted[name]])
        squared = ((j_hat - j_sim) ** 2).sum(axis=(0, 2, 3))
        norm = (j_sim**2).sum(axis=(0, 2, 3))
        per_k = np.sqrt(squared / norm)
        grad = loss_gradient(j_hat, q_hat, q_star, args.gamma)
        cos = (grad * grad_sim).sum(1) / (np.linalg.norm(grad, axis=1) * np.linalg.norm(grad_sim, axis=1) + 1e-12)
        cells = " | ".join(f"{per_k[k - 1]:.3f}" for k in (1, 5, 10, 20) if k <= horizon)
        mpe = np.rad2deg(np.abs(wrap(q_hat - q_sim)).mean())
        overall = np.sqrt(squared.sum() / norm.sum())
        print(f"| {name} | {mpe:.3f} | {overall:.3f} | {cells} | {np.median(cos):.3f} | {cos.mean():.3f} |")
    if policies:
        print("\n| judged by | policy | L_track (1e-5 rad²) | L_reg (1e-5 rad²) | 20-step MAE (°) |")
        print("|---|---|---:|---:|---:|")
        for (judge, policy_name), terms in judged.items():
            l_track, l_reg, mae = np.concatenate(terms).mean(0)
            print(f"| {judge} | {policy_name} | {l_track * 1e5:.1f} | {l_reg * 1e5:.1f} | {np.rad2deg(mae):.3f} |")


if __name__ == "__main__":
    main()

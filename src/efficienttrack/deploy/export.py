"""``efficienttrack export``: a trained policy as an ONNX graph and the contract that says how to feed it.

The graph is the policy's whole forward pass (:meth:`~efficienttrack.learn.policy.AdjustmentPolicy.forward`): relative
features, their standardization with the statistics of the training windows, the MLP and the bounded output
``tanh × max_adjust``, float32, with a dynamic batch axis. The torch-free runtime
(:mod:`efficienttrack.deploy.onnx_runtime`) reads the export back; the contract's format is defined there.

The exporter is torch's TorchScript-based one (``torch.onnx.export(..., dynamo=False)``): the policy is a plain
feed-forward graph it handles fully, and it needs no package beyond ``onnx`` (the ``torch.export``-based exporter,
torch's default since 2.9, needs ``onnxscript`` as well). Before anything is written the graph is run in ONNX
Runtime on windows spread over the joint ranges and compared with the torch policy; an export that differs by more
than :data:`PARITY_TOLERANCE` is refused.
"""

from __future__ import annotations

import copy
import hashlib
import io
import json
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch

import efficienttrack
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import atomic_write, write_json
from efficienttrack.core.joints import DT, JOINT_NAMES
from efficienttrack.core.settings import plain_form
from efficienttrack.deploy.onnx_runtime import (
    CONTRACT_FILE,
    CONTRACT_FORMAT,
    CONTRACT_VERSION,
    INPUT_NAMES,
    ONNX_FILE,
    OUTPUT_NAME,
    load_onnx_policy,
)
from efficienttrack.learn.checkpoints import config_path
from efficienttrack.learn.policy import AdjustmentPolicy, seen_lengths

OPSET = 17
"""ONNX opset of the graph (17: the first with LayerNormalization as one operator)."""
PARITY_TOLERANCE = 1e-5
"""Largest difference (rad) between the graph in ONNX Runtime and the torch policy an export accepts."""
CHECK_WINDOWS = 256
"""Windows the export is checked on before it is written."""


def check_windows(h: int, F: int, n: int = CHECK_WINDOWS, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Seeded windows spread over the joint ranges (the swing around ±π too), to compare the graph with the policy.

    Args:
        h: history length.
        F: future desired positions.
        n: windows.
        seed: seeds the generator.

    Returns:
        obs_hist (n, h, 8), qref_hist (n, h, 4), qdes_future (n, F, 4), float32 [rad, rad/s].
    """
    rng = np.random.default_rng(seed)
    q = rng.uniform(-np.pi, np.pi, (n, 1, 4)) + np.cumsum(rng.normal(0, 0.02, (n, h, 4)), axis=1)
    obs = np.concatenate([q, rng.normal(0, 0.5, (n, h, 4))], axis=2)
    q_ref = q + rng.normal(0, 0.05, (n, h, 4))
    q_des = q[:, -1:] + np.cumsum(rng.normal(0, 0.02, (n, F, 4)), axis=1)
    return obs.astype(np.float32), q_ref.astype(np.float32), q_des.astype(np.float32)


def checkpoint_source(path: str | Path) -> dict[str, Any]:
    """Where a policy checkpoint came from, for the contract: its file, weights hash, provenance and last evaluation.

    Args:
        path: the policy checkpoint (``policy.pt``); its JSON config lies next to it (already checked by loading it).

    Returns:
        ``{"checkpoint": file name, "weights_sha256": …, "training_fingerprint": …, "provenance": …, "evaluation": …}``
        as its JSON config states them (``training_fingerprint`` is None for a checkpoint saved without one,
        ``evaluation`` for one never measured: :func:`~efficienttrack.learn.checkpoints.record_evaluation`).
    """
    meta = json.loads(config_path(path).read_text())
    facts = ("weights_sha256", "training_fingerprint", "provenance", "evaluation")
    return {"checkpoint": Path(path).name, **{name: meta.get(name) for name in facts}}


def contract(policy: AdjustmentPolicy, onnx_sha256: str, source: dict[str, Any] | None) -> dict[str, Any]:
    """The contract ``policy.json`` of an export (read back by :func:`efficienttrack.deploy.onnx_runtime.read_contract`).

    Args:
        policy: the exported policy.
        onnx_sha256: SHA-256 of the graph's bytes.
        source: where the policy came from (:func:`checkpoint_source`), or None.

    Returns:
        The JSON-serializable contract.
    """
    h, F = seen_lengths(policy.cfg)
    return {
        "format": CONTRACT_FORMAT,
        "format_version": CONTRACT_VERSION,
        "onnx": ONNX_FILE,
        "onnx_sha256": onnx_sha256,
        "opset": OPSET,
        "joint_order": list(JOINT_NAMES),
        "units": {"angle": "rad", "angular_velocity": "rad/s", "time": "s"},
        "dt": DT,
        "history_length": h,
        "future_length": F,
        "inputs": [
            {
                "name": INPUT_NAMES[0],
                "shape": ["batch", h, 8],
                "dtype": "float32",
                "meaning": "o_{t-h+1} ... o_t, oldest first: measured positions q (rad, 4 joints) then velocities "
                "qd (rad/s, 4 joints); at an episode start padded with o_0",
            },
            {
                "name": INPUT_NAMES[1],
                "shape": ["batch", h, 4],
                "dtype": "float32",
                "meaning": "q^r_{t-h+1} ... q^r_t, oldest first: the references sent (rad); at an episode start padded "
                "with q_0, the measured start position",
            },
            {
                "name": INPUT_NAMES[2],
                "shape": ["batch", F, 4],
                "dtype": "float32",
                "meaning": "q*_{t+1} ... q*_{t+F}: the next desired positions (rad), past the reference's end repeating "
                "its last one",
            },
        ],
        "output": {
            "name": OUTPUT_NAME,
            "shape": ["batch", 4],
            "dtype": "float32",
            "meaning": "a_t (rad): send q^r_{t+1} = q*_{t+1} + a_t, through the guard",
        },
        "max_adjust": list(policy.cfg.max_adjust),
        "bound": "the output is tanh(·) × max_adjust per joint inside the graph; the runtime's guard takes its limits "
        "from the machine, and max_adjust here can only tighten its adjustment bound",
        "standardization": "inside the graph: features standardized with the training windows' mean and std",
        "policy_config": plain_form(policy.cfg),
        "source": source,
        "package_version": efficienttrack.__version__,
        "torch_version": torch.__version__,
    }


def export_policy(policy: AdjustmentPolicy, out: str | Path, source: dict[str, Any] | None = None) -> Path:
    """Write ``policy.onnx`` and ``policy.json`` into ``out``, after checking the graph against the policy.

    The graph is written first and the contract, which holds its SHA-256, last (a folder whose contract is
    missing or does not match its graph is refused by the runtime); both are removed again when the check fails.

    Args:
        policy: the trained policy (any device; it is copied to the CPU, the original is not changed).
        out: the export folder (created when missing; the caller checks it before the work).
        source: where the policy came from (:func:`checkpoint_source`), stated in the contract, or None.

    Returns:
        The export folder.

    Raises:
        EfficientTrackError: the exporter fails, or the graph in ONNX Runtime differs from the policy by more than
            :data:`PARITY_TOLERANCE`.
    """
    out = Path(out)
    cpu = copy.deepcopy(policy).float().cpu().eval()
    h, F = seen_lengths(cpu.cfg)
    windows = check_windows(h, F)
    example = tuple(torch.from_numpy(x[:2]) for x in windows)
    buffer = io.BytesIO()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the TorchScript exporter's deprecation notices
            # torch annotates f as a path; the TorchScript exporter (dynamo=False) writes to a file object too.
            torch.onnx.export(
                cpu,
                example,
                buffer,  # type: ignore[arg-type]
                input_names=list(INPUT_NAMES),
                output_names=[OUTPUT_NAME],
                dynamic_axes={name: {0: "batch"} for name in (*INPUT_NAMES, OUTPUT_NAME)},
                opset_version=OPSET,
                dynamo=False,
            )
    except Exception as exc:  # the exporter's errors come from deep inside torch
        raise EfficientTrackError(f"export: torch could not export the policy to ONNX ({type(exc).__name__}: {exc})") from exc
    graph = buffer.getvalue()
    digest = hashlib.sha256(graph).hexdigest()
    atomic_write(out / ONNX_FILE, lambda f: f.write(graph))
    write_json(out / CONTRACT_FILE, contract(cpu, digest, source))
    try:
        with torch.no_grad():
            expected = cpu(*(torch.from_numpy(x) for x in windows)).numpy()
        differs = float(np.max(np.abs(load_onnx_policy(out)(*windows) - expected)))
        if not differs <= PARITY_TOLERANCE:
            raise EfficientTrackError(
                f"export: the ONNX graph differs from the policy by {differs:.3g} rad (> {PARITY_TOLERANCE:g}); not written"
            )
    except BaseException:
        for name in (CONTRACT_FILE, ONNX_FILE):
            (out / name).unlink(missing_ok=True)
        raise
    return out

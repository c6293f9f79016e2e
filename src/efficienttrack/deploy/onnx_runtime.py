"""The guarded policy without the training stack: an ONNX export run by ONNX Runtime, numpy only, no torch.

An export (``efficienttrack export``, :mod:`efficienttrack.deploy.export`) is a folder with two files:

- ``policy.onnx``: the policy's whole forward pass, relative features, their standardization and the bounded
  output ``tanh × max_adjust``, float32, with a dynamic batch axis;
- ``policy.json``: the contract, read here: joint order, units, control period, history and future lengths,
  the graph's inputs and output, the bound, the policy config, the checkpoint it came from, the package version
  and the SHA-256 of ``policy.onnx`` (checked before the graph is loaded).

:class:`OnnxRuntime` is :class:`~efficienttrack.deploy.guard.GuardedRuntime` (the one guard, the same histories and the
same ``start``/``step``/``stop`` and :class:`~efficienttrack.deploy.episodes.Sent` as the torch runtime, with the same
optional time stamps ``t``) around the exported graph::

    with OnnxRuntime(load_onnx_policy("export/"), limits=GuardLimits.load("xe75_limits.yaml")) as rt:
        rt.start(read_obs())                                                     # (1, 8)
        for t in range(T):
            sent = rt.step(read_obs(), q_des[None, t + 1 : t + 1 + rt.future_length])
            send_reference(sent.q_ref[0])

The core install (``pip install efficienttrack``: numpy, PyYAML, rich, Typer, onnxruntime) runs it; importing this
module imports no torch (``tests/test_export.py`` runs it with torch made unimportable, ``tests/test_wheel.py`` on the
core install).
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.joints import JOINT_NAMES, N_JOINTS, OBS_DIM
from efficienttrack.deploy.guard import MAX_GAP, GuardedRuntime
from efficienttrack.systems.limits import GuardLimits

ONNX_FILE = "policy.onnx"
"""The graph's file name in an export folder."""
CONTRACT_FILE = "policy.json"
"""The contract's file name in an export folder."""
CONTRACT_FORMAT = "efficienttrack-policy-onnx"
"""``format`` of a contract, so that another JSON file is not taken for one."""
CONTRACT_VERSION = 1
"""``format_version`` of the contracts this version writes and reads."""
INPUT_NAMES = ("obs_hist", "qref_hist", "qdes_future")
"""The graph's inputs, in order (shapes in the contract's ``inputs``)."""
OUTPUT_NAME = "adjustment"
"""The graph's output, a_t (batch, 4) rad."""
MAX_LENGTH = 400
"""Longest history or future a contract may state (the configs' bound, 20 s at 20 Hz)."""


@dataclass(frozen=True)
class Contract:
    """What the runtime needs from ``policy.json`` (validated); the whole file is kept in :attr:`data`.

    Attributes:
        history_length: h, length of ``obs_hist`` and ``qref_hist``.
        future_length: F, length of ``qdes_future``.
        max_adjust: (4,) rad, the bound of the graph's output (the guard's bound can only be tighter).
        dt: control period the policy was trained for, s.
        onnx_sha256: SHA-256 of ``policy.onnx``.
        data: the whole contract as read.
    """

    history_length: int
    future_length: int
    max_adjust: tuple[float, ...]
    dt: float
    onnx_sha256: str
    data: dict[str, Any]


def read_contract(folder: str | Path) -> Contract:
    """Read and check the contract ``policy.json`` of an export folder.

    Args:
        folder: the export folder (``efficienttrack export --out``).

    Returns:
        The contract.

    Raises:
        EfficientTrackError: the file is missing, not JSON, not a contract, of another format version, or a field the
            runtime relies on is missing or wrong (named).
    """
    path = Path(folder) / CONTRACT_FILE
    if not path.is_file():
        raise EfficientTrackError(f"{path}: no such file; an export folder holds {ONNX_FILE} and {CONTRACT_FILE}")
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise EfficientTrackError(f"{path}: not a readable JSON file ({exc})") from exc
    if not isinstance(data, dict) or data.get("format") != CONTRACT_FORMAT:
        raise EfficientTrackError(f"{path}: not an EfficientTrack policy export (field 'format' is not '{CONTRACT_FORMAT}')")
    if data.get("format_version") != CONTRACT_VERSION:
        raise EfficientTrackError(
            f"{path}: field 'format_version' is {data.get('format_version')!r}, this version reads {CONTRACT_VERSION}; "
            "export the policy again"
        )

    def field(name: str, ok: Any, expected: str) -> Any:
        value = data.get(name)
        if not ok(value):
            raise EfficientTrackError(f"{path}: field '{name}' must be {expected}, got {value!r}")
        return value

    def length(v: Any) -> bool:
        return isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= MAX_LENGTH

    def positive(v: Any) -> bool:
        return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) and v > 0

    def bounds(v: Any) -> bool:
        return isinstance(v, list) and len(v) == N_JOINTS and all(map(positive, v))

    field("joint_order", lambda v: v == list(JOINT_NAMES), f"{list(JOINT_NAMES)}")
    return Contract(
        history_length=field("history_length", length, f"an integer in [1, {MAX_LENGTH}]"),
        future_length=field("future_length", length, f"an integer in [1, {MAX_LENGTH}]"),
        max_adjust=tuple(field("max_adjust", bounds, "4 positive numbers (rad)")),
        dt=field("dt", positive, "a positive number (s)"),
        onnx_sha256=field("onnx_sha256", lambda v: isinstance(v, str) and len(v) == 64, "a SHA-256 hex digest"),
        data=data,
    )


class OnnxPolicy:
    """An exported policy in ONNX Runtime on the CPU, called as the guard calls a policy (``guard.PolicyCall``).

    Args:
        folder: the export folder; ``policy.onnx`` must match the contract's SHA-256 (it is read once, hashed, and
            the session built from those bytes, so no other file is consulted).
        threads: ONNX Runtime intra-op threads (1 keeps a control computer's other cores free and the timing steady).

    Attributes:
        contract: the export's :class:`Contract`.
    """

    def __init__(self, folder: str | Path, threads: int = 1) -> None:
        if not isinstance(threads, int) or isinstance(threads, bool) or threads < 1:
            raise EfficientTrackError(f"ONNX Runtime threads must be an integer ≥ 1, got {threads!r}")
        self.contract = read_contract(folder)
        path = Path(folder) / ONNX_FILE
        try:
            graph = path.read_bytes()
        except OSError as exc:
            raise EfficientTrackError(f"{path}: cannot read the exported graph ({exc.strerror or exc})") from exc
        if hashlib.sha256(graph).hexdigest() != self.contract.onnx_sha256:
            raise EfficientTrackError(
                f"{path}: does not match the SHA-256 in {CONTRACT_FILE} (changed or damaged); export the policy again"
            )
        options = onnxruntime.SessionOptions()
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1
        options.execution_mode = onnxruntime.ExecutionMode.ORT_SEQUENTIAL
        options.log_severity_level = 3
        try:
            self.session = onnxruntime.InferenceSession(graph, options, providers=["CPUExecutionProvider"])
        except Exception as exc:  # ONNX Runtime raises its own exception types for every kind of bad graph
            raise EfficientTrackError(f"{path}: ONNX Runtime cannot load the graph ({exc})") from exc
        h, F = self.contract.history_length, self.contract.future_length
        expected = {"obs_hist": [h, OBS_DIM], "qref_hist": [h, N_JOINTS], "qdes_future": [F, N_JOINTS]}
        found = {i.name: list(i.shape[1:]) for i in self.session.get_inputs()}
        outputs = [o.name for o in self.session.get_outputs()]
        if found != expected or outputs != [OUTPUT_NAME]:
            raise EfficientTrackError(
                f"{path}: the graph's inputs {found} and outputs {outputs} are not those of {CONTRACT_FILE} "
                f"(inputs {expected} after the batch axis, output ['{OUTPUT_NAME}'])"
            )

    def __call__(self, obs_hist: np.ndarray, qref_hist: np.ndarray, qdes_future: np.ndarray) -> np.ndarray:
        """a_t for a batch of B windows, as the torch policy computes it (float32 inside).

        Args:
            obs_hist: (B, h, 8) [rad, rad/s], ``o_{t−h+1} … o_t``.
            qref_hist: (B, h, 4) rad, ``q^r_{t−h+1} … q^r_t``.
            qdes_future: (B, F, 4) rad, ``q*_{t+1} … q*_{t+F}``.

        Returns:
            (B, 4) float32 rad, the adjustment, |a| < max_adjust per joint.
        """
        feeds = {
            name: np.ascontiguousarray(x, dtype=np.float32)
            for name, x in zip(INPUT_NAMES, (obs_hist, qref_hist, qdes_future), strict=True)
        }
        return self.session.run([OUTPUT_NAME], feeds)[0]


class OnnxRuntime(GuardedRuntime):
    """Algorithm 2 with an exported policy, without torch: the guarded step of :class:`~.guard.GuardedRuntime`.

    Same ``start``/``step``/``stop``, :class:`~efficienttrack.deploy.episodes.Sent`, counters and guard as
    :class:`efficienttrack.deploy.runtime.Runtime`; given the same limits and inputs it sends the same references (up to
    float32 round-off of the graph, ≤ 1e-5 rad).

    Args:
        policy: the exported policy (:class:`OnnxPolicy`).
        limits: the machine's limits (a system's ``limits``, or :meth:`GuardLimits.load`), a required keyword;
            ``limits=None`` is the explicit choice of the default limits. The contract's ``max_adjust`` only tightens
            ``limits.max_adjust``.
        dt: control period, s (for the observation jump check, and the period a ``step`` without ``t`` stands for); the
            contract's when None.
        max_gap: periods between two time-stamped observations (``step(..., t=...)``) beyond which samples count as
            dropped: the step falls back and the histories start afresh (:data:`~efficienttrack.deploy.guard.MAX_GAP`).
    """

    def __init__(
        self, policy: OnnxPolicy, *, limits: GuardLimits | None, dt: float | None = None, max_gap: float = MAX_GAP
    ) -> None:
        contract = policy.contract
        lengths = (contract.history_length, contract.future_length)
        super().__init__(policy, lengths, contract.max_adjust, limits, contract.dt if dt is None else dt, max_gap)
        self.policy = policy


def load_onnx_policy(folder: str | Path, threads: int = 1) -> OnnxPolicy:
    """Load an export folder written by ``efficienttrack export`` (checked against its contract).

    Args:
        folder: the folder holding ``policy.onnx`` and ``policy.json``.
        threads: ONNX Runtime intra-op threads.

    Returns:
        The policy, callable on numpy histories.

    Raises:
        EfficientTrackError: ``folder`` is a torch checkpoint (``policy.pt``: export it first), or not an export folder.
    """
    if Path(folder).is_file() and Path(folder).suffix == ".pt":
        raise EfficientTrackError(
            f"{folder}: a torch checkpoint, which this runtime does not read; export it where the train extra is installed "
            f"(efficienttrack export --policy {folder} --out DIR) and load DIR"
        )
    return OnnxPolicy(folder, threads)

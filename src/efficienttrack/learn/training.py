"""Training bookkeeping shared by the model and the policy: the schedule settings, scalar logs and :class:`TrainLoop`.

``TrainLoop`` handles resume, progress, the learning-rate schedule, the scalar log (:class:`TrainLog`: CSV and
TensorBoard, every scalar listed in docs/logged-metrics.md), held-out figures at intervals and atomic saves, so
that ``dynamics.train_model`` and ``policy.train_policy`` show only the algorithm. The network files themselves are
:mod:`efficienttrack.learn.checkpoints`.
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from efficienttrack.core.configfile import check_seed
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import atomic_write
from efficienttrack.core.progress import ProgressDisplay
from efficienttrack.core.provenance import MAX_SHOWN, differences
from efficienttrack.core.settings import plain_form
from efficienttrack.data.records import EpisodeRecord
from efficienttrack.learn.checkpoints import check_finite, load_tensors


def fingerprint(records: Sequence[EpisodeRecord], seed: int, *networks: nn.Module | None) -> str:
    """SHA-256 identity of a training run's inputs: the records' arrays, the seed and the networks it starts from.

    Args:
        records: the training episodes (``q``, ``qd``, ``q_ref``, ``q_des`` are hashed).
        seed: the run's seed.
        *networks: networks the run depends on, in a fixed order: one it trains through (the model, for a
            policy) and the weights it starts from (a warm start); None for one that is absent.

    Returns:
        The hex digest.
    """
    digest = hashlib.sha256(str(seed).encode())
    for record in records:
        for array in (record.q, record.qd, record.q_ref, record.q_des):
            digest.update(np.ascontiguousarray(array).tobytes())
    for network in networks:
        digest.update(b"network" if network is not None else b"none")
        for name, tensor in (network.state_dict() if network is not None else {}).items():
            digest.update(name.encode())
            digest.update(tensor.detach().cpu().numpy().tobytes())
    return digest.hexdigest()


PROGRESS_EVERY = 10
"""Steps between progress refreshes."""
EVALUATIONS = 10
"""Held-out evaluations of a run whose config leaves ``eval_every`` unset (one every tenth of the run)."""
HELD_OUT_STEPS = 4096
"""Most recorded steps of held-out episodes evaluated (:func:`held_out_subset`), bounding each evaluation's cost."""
SCALARS_CSV = "scalars.csv"
"""The scalar log in a run's log folder: columns ``step,tag,value`` (docs/logged-metrics.md)."""
LOSS_TAG = "train/loss"
"""Scalar tag of the loss of each optimizer step."""
LR_TAG = "train/lr"
"""Scalar tag of the learning rate of each optimizer step."""


def held_out_subset(records: Sequence[EpisodeRecord], max_steps: int = HELD_OUT_STEPS) -> list[EpisodeRecord]:
    """Evenly spaced episodes of ``records`` with at most ``max_steps`` recorded steps together (at least one episode).

    Deterministic: the same records give the same subset.

    Args:
        records: the held-out episodes.
        max_steps: budget of recorded steps.

    Returns:
        The chosen episodes, in their order (all of them when they fit).
    """
    if not records:
        return []
    lengths = np.array([len(r) for r in records])
    first_guess = min(len(records), math.ceil(len(records) * max_steps / lengths.sum()))
    for count in range(first_guess, 0, -1):
        chosen = np.unique(np.linspace(0, len(records) - 1, count).round().astype(int))
        if count == 1 or lengths[chosen].sum() <= max_steps:
            break
    return [records[i] for i in chosen]


def read_scalars(path: str | Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Read a ``scalars.csv`` written by :class:`TrainLog` (or the log folder holding it).

    Args:
        path: the CSV file, or the folder holding :data:`SCALARS_CSV`.

    Returns:
        tag → ((K,) int64 optimizer steps, (K,) float64 values), in step order.

    Raises:
        EfficientTrackError: a missing file or a line that is not ``step,tag,value``.
    """
    path = Path(path)
    path = path / SCALARS_CSV if path.is_dir() else path
    if not path.is_file():
        raise EfficientTrackError(f"{path}: no such scalar log")
    rows: dict[str, tuple[list[int], list[float]]] = {}
    for number, (step, tag, value) in enumerate(_rows(path), start=2):
        try:
            steps, values = rows.setdefault(tag, ([], []))
            steps.append(int(step))
            values.append(float(value))
        except ValueError as exc:
            raise EfficientTrackError(f"{path}: line {number}: expected step,tag,value ({exc})") from exc
    return {tag: (np.array(steps, dtype=np.int64), np.array(values)) for tag, (steps, values) in rows.items()}


def _rows(path: Path) -> list[list[str]]:
    """The data rows of a scalar CSV (header checked)."""
    with path.open(newline="") as f:
        lines = list(csv.reader(f))
    if not lines or lines[0] != ["step", "tag", "value"]:
        raise EfficientTrackError(f"{path}: not a scalar log (expected the header step,tag,value)")
    if any(len(row) != 3 for row in lines[1:]):
        raise EfficientTrackError(f"{path}: every line must hold step,tag,value")
    return lines[1:]


def _rows_through(path: Path, start: int) -> list[list[str]]:
    """The rows of steps ≤ ``start`` of an interrupted run's CSV (a torn last line, written later, is dropped)."""
    with path.open(newline="") as f:
        rows = list(csv.reader(f))[1:]
    return [row for row in rows if len(row) == 3 and row[0].isdigit() and int(row[0]) <= start]


class TrainLog:
    """Scalars of a training run, per optimizer step, to ``scalars.csv`` and TensorBoard event files in one folder.

    ``step`` is the number of optimizer steps done: the loss of the k-th step is logged at k, a held-out
    figure measured after k steps at k. CSV rows are flushed as they are written, TensorBoard events every 10 s
    and by :meth:`flush`. Opened at ``start`` (a run resumed from a state saved after ``start`` steps), the CSV
    keeps only the rows of steps ≤ ``start`` and TensorBoard hides the events after ``start`` (``purge_step``),
    so a resumed run logs what an uninterrupted one does.

    Args:
        folder: the log folder (created).
        start: optimizer steps already done.
    """

    def __init__(self, folder: str | Path, start: int) -> None:
        from torch.utils.tensorboard import SummaryWriter  # imports tensorboard: only for runs that log

        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        path = self.folder / SCALARS_CSV
        kept = _rows_through(path, start) if start > 0 and path.is_file() else []
        atomic_write(path, lambda f: csv.writer(f).writerows([["step", "tag", "value"], *kept]), mode="w")
        self._csv = path.open("a", newline="")
        self._writer = csv.writer(self._csv)
        self._tensorboard = SummaryWriter(str(self.folder), purge_step=start + 1, flush_secs=10)

    def scalar(self, step: int, tag: str, value: float) -> None:
        """Log ``value`` of ``tag`` at optimizer step ``step``.

        Args:
            step: optimizer steps done (1 for the first step).
            tag: the scalar's name (docs/logged-metrics.md).
            value: its value.
        """
        self._writer.writerow([step, tag, repr(float(value))])
        self._csv.flush()
        self._tensorboard.add_scalar(tag, value, step)

    def flush(self) -> None:
        """Write everything logged so far to disk."""
        self._csv.flush()
        self._tensorboard.flush()

    def close(self) -> None:
        """Flush and close the files."""
        self._csv.close()
        self._tensorboard.close()


class TrainLoop:
    """The bookkeeping around a BPTT loop: steps, sampling RNG, learning rate, logs, held-out figures, progress, resume.

    The training state (weights, optimizer, sampling generator, losses) is saved atomically every
    ``cfg.save_every`` steps and at the end; an existing state of the same run is resumed from.
    With a log folder, every step's loss and learning rate and every held-out figure go to a :class:`TrainLog`.

    Iterate over it to get the step numbers still to do; call :meth:`record` once per step.

    Args:
        kind: ``"model"`` or ``"policy"`` (checked when resuming).
        cfg: the frozen config (needs ``lr``, ``cosine_decay``, ``save_every``, ``eval_every``); a resumed state
            must have the same.
        total: optimizer steps of the whole run.
        module: the network being trained.
        optimizer: its optimizer.
        seed: seeds the window-sampling generator.
        checkpoint: training-state file (resumed when it exists), or None.
        progress: show progress (a rich bar on a terminal, plain lines otherwise).
        inputs: fingerprint of what the run learns from (:func:`fingerprint`); a saved state made from other
            inputs is refused instead of being resumed.
        log_dir: folder for ``scalars.csv`` and TensorBoard event files, or None for no log.
        evaluate: computes the held-out figures ({tag: value}) of the module as it is; with a log folder, called
            after every ``cfg.eval_every`` steps (None: every tenth of the run) and after the last step.
    """

    def __init__(
        self,
        kind: str,
        cfg: Any,
        total: int,
        module: nn.Module,
        optimizer: torch.optim.Optimizer,
        seed: int,
        checkpoint: str | Path | None,
        progress: bool,
        inputs: str = "",
        log_dir: str | Path | None = None,
        evaluate: Callable[[], dict[str, float]] | None = None,
    ) -> None:
        self.kind, self.cfg, self.total, self.inputs = kind, cfg, total, inputs
        self.module, self.optimizer = module, optimizer
        self.checkpoint = None if checkpoint is None else Path(checkpoint)
        self.progress = progress
        self.generator = torch.Generator().manual_seed(check_seed(seed, f"{kind} training: seed"))
        self._losses = np.full(total, np.nan)
        self.start = 0
        self._config = json.dumps(plain_form(cfg), sort_keys=True)
        self.log_dir = None if log_dir is None else Path(log_dir)
        self.evaluate = evaluate
        self.eval_every = cfg.eval_every if cfg.eval_every is not None else math.ceil(total / EVALUATIONS)
        self._log: TrainLog | None = None
        if self.checkpoint is not None and self.checkpoint.exists():
            self._resume(self.checkpoint)

    def _resume(self, checkpoint: Path) -> None:
        """Load the saved training state ``checkpoint``, refusing one from another kind or config."""
        state = load_tensors(checkpoint)
        same = (state.get("kind"), state.get("config"), state.get("total"), state.get("inputs"))
        if same != (self.kind, self._config, self.total, self.inputs):
            raise EfficientTrackError(
                f"{self.checkpoint}: training state of another run ({self._difference(state)}); delete it (--force on the "
                "command line) to start afresh, or train with the settings it was made with"
            )
        fix = "delete it (--force on the command line) to start this training afresh"
        try:
            self.module.load_state_dict(state["module"])
            self.optimizer.load_state_dict(state["optimizer"])
            self.generator.set_state(state["generator"])
            step, losses = state["step"], state["losses"]
        except (KeyError, RuntimeError, ValueError, TypeError) as exc:
            raise EfficientTrackError(f"{self.checkpoint}: unreadable training state (missing or bad {exc}); {fix}") from exc
        if not isinstance(step, int) or isinstance(step, bool) or not 0 <= step <= self.total:
            raise EfficientTrackError(f"{self.checkpoint}: training state at step {step!r}, outside 0 … {self.total}; {fix}")
        if not isinstance(losses, torch.Tensor) or losses.shape != (self.total,) or not losses[:step].isfinite().all():
            raise EfficientTrackError(f"{self.checkpoint}: training state lacks the losses of its {step} steps; {fix}")
        try:
            check_finite(self.module, f"{self.checkpoint}: training state refused")
        except EfficientTrackError as exc:
            raise EfficientTrackError(f"{exc}; {fix}") from exc
        self.start = step
        self._losses[:step] = losses.double().numpy()[:step]

    def _difference(self, state: dict[str, Any]) -> str:
        """What makes a saved training state another run's: the kind, the config's fields, the steps or the inputs."""
        if state.get("kind") != self.kind:
            return f"a {state.get('kind')} training, this is a {self.kind} training"
        if state.get("config") != self._config:
            try:
                saved = json.loads(state["config"])
            except (TypeError, ValueError):
                return "its config is unreadable"
            return "config " + "; ".join(differences(saved, json.loads(self._config))[:MAX_SHOWN])
        if state.get("total") != self.total:
            return f"{state.get('total')} optimizer steps there, {self.total} now"
        return "other data, seed or starting network"

    def save(self, step: int) -> None:
        """Flush the log, then write the training state after ``step`` steps atomically (no-op without a checkpoint).

        Args:
            step: optimizer steps done.
        """
        if self._log is not None:
            self._log.flush()
        if self.checkpoint is None:
            return
        check_finite(self.module, f"{self.checkpoint}: {self.kind} training state after {step} steps not saved")
        state = {
            "kind": self.kind,
            "config": self._config,
            "total": self.total,
            "inputs": self.inputs,
            "step": step,
            "module": self.module.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "generator": self.generator.get_state(),
            "losses": torch.as_tensor(self._losses),
        }
        atomic_write(self.checkpoint, lambda f: torch.save(state, f))

    def sample(self, n: int, batch: int) -> torch.Tensor:
        """(batch,) int64 CPU indices drawn uniformly from range(n) with the loop's generator.

        Args:
            n: number of windows to draw from.
            batch: indices to draw.
        """
        return torch.randint(n, (batch,), generator=self.generator)

    def set_lr(self, step: int) -> None:
        """Set the optimizer's learning rate for ``step``: ``cfg.lr``, cosine-decayed, ramped up over ``cfg.warmup``.

        The cosine decays it to 0 over the run when ``cfg.cosine_decay``; the ramp rises linearly over the first
        ``cfg.warmup`` share of the steps.

        Args:
            step: the optimizer step about to be taken (0-based).
        """
        lr = self.cfg.lr * (0.5 * (1 + math.cos(math.pi * step / self.total)) if self.cfg.cosine_decay else 1.0)
        ramp = math.ceil(self.cfg.warmup * self.total)
        lr *= min(1.0, (step + 1) / ramp) if ramp else 1.0
        for group in self.optimizer.param_groups:
            group["lr"] = lr

    def record(self, step: int, loss: float) -> None:
        """Log the loss and learning rate of ``step`` (0-based), the held-out figures when due, and save when due.

        Args:
            step: the optimizer step just taken (0-based; logged as ``step + 1`` steps done).
            loss: its loss.
        """
        if not math.isfinite(loss):
            kept = f"; the training state in {self.checkpoint} is kept" if self.checkpoint and self.checkpoint.exists() else ""
            raise EfficientTrackError(
                f"{self.kind} training stopped: the loss is {loss} at step {step + 1} of {self.total} (check the training "
                f"data for absurd values, lower lr ({self.cfg.lr}) or set grad_clip ({self.cfg.grad_clip})); nothing was "
                f"saved from this step on{kept}"
            )
        self._losses[step] = loss
        done = step + 1
        if self._log is not None:
            self._log.scalar(done, LOSS_TAG, loss)
            self._log.scalar(done, LR_TAG, self.optimizer.param_groups[0]["lr"])
        if self._log is not None and self.evaluate is not None and (done % self.eval_every == 0 or done == self.total):
            for tag, value in self.evaluate().items():
                self._log.scalar(done, tag, value)
            self.module.train()
        if done % self.cfg.save_every == 0 and done < self.total:
            self.save(done)

    def losses(self) -> np.ndarray:
        """(total,) the loss of every step (NaN for steps not run)."""
        return self._losses.copy()

    def __iter__(self) -> Iterator[int]:
        """Yield the remaining step numbers, logging and showing progress; save the final state at the end."""
        if self.start >= self.total:
            return
        self.module.train()
        self._log = None if self.log_dir is None else TrainLog(self.log_dir, self.start)
        try:
            with ProgressDisplay(self.progress, transient=False) as bar:
                resumed = f" (resumed at step {self.start:,} from {self.checkpoint})" if self.start else ""
                task = bar.add_task(f"train {self.kind}{resumed}", total=self.total, completed=self.start, loss=float("nan"))
                for step in range(self.start, self.total):
                    yield step
                    if (step + 1) % PROGRESS_EVERY == 0 or step + 1 == self.total:
                        recent = self._losses[max(self.start, step + 1 - PROGRESS_EVERY) : step + 1]
                        bar.update(task, completed=step + 1, loss=float(np.mean(recent)))
            self.save(self.total)
        finally:
            if self._log is not None:
                self._log.close()
                self._log = None

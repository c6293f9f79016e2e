"""A run's ledger: which stages finished, with their facts, and the wall time each stage and the whole run took.

A run folder is built stage by stage. A stage writes its marker ``<folder>/stages/<name>.json`` last, so a rerun skips
what finished and resumes what did not; round k ≥ 2 keeps its markers in ``OUT/rounds/<k>/stages``. Every marker
holds the stage's ``seconds``.

The run's time counts all its invocations, not the time between a kill and the rerun: ``OUT/stages/time_spent.json``
(:data:`SPENT`) is written when an invocation starts, every :data:`HEARTBEAT` s from a thread (a SIGKILL loses at most
that much) and when it stops. A stage that a kill split took the run's time from its first start to its end, the restart
and the work done again included: a resumed training's own clock sees only its last part, and a time budget planned
from that would take the machine for faster than it is.
"""

from __future__ import annotations

import contextlib
import json
import math
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import write_json

T = TypeVar("T")

ROUNDS = "rounds"
"""Folder of the rounds after the first in a run folder: ``rounds/<k>/``."""
SPENT = "time_spent"
"""The run's wall time so far, ``OUT/stages/time_spent.json`` (not a stage: rewritten as the run goes):
``{"spent_seconds", "invocations", "finished": whether the last invocation finished the run, "work": {stage: {"began":
spent seconds when it began, "invocation"}} for the stages begun and not finished}``."""
HEARTBEAT = 2.0
"""Seconds between two writes of :data:`SPENT` while a run goes on."""


class Ledger:
    """The finished-stage markers of a run folder and its rounds, and the run's time.

    Args:
        out: the run folder.
        started: ``time.perf_counter()`` when this invocation began; its time is added to what the earlier invocations
            spent (none when the last one finished the run: a rerun that adds rounds counts its own minutes).

    Raises:
        EfficientTrackError: :data:`SPENT` is unreadable.
    """

    def __init__(self, out: Path, started: float) -> None:
        self.out, self.started = out, started
        self.path = out / "stages" / f"{SPENT}.json"
        spent, invocations, finished, self.work = read_spent(self.path)
        self.spent_before = 0.0 if finished else spent
        self.invocation = invocations + 1
        self.finished = False
        self.skipped: list[str] = []
        """Stages found finished by this invocation (round k's as ``rounds/<k>/<name>``)."""
        self.facts: dict[str, dict[str, Any]] = {}
        """Facts of every stage this invocation ran or found finished, by the same keys."""
        self._lock = threading.RLock()

    def folder(self, k: int = 1) -> Path:
        """Round k's folder: the run folder for round 1, ``OUT/rounds/<k>`` after it."""
        return self.out if k == 1 else self.out / ROUNDS / str(k)

    def seconds_spent(self) -> float:
        """Wall seconds the run has spent so far: its earlier invocations' and this one's."""
        return self.spent_before + (time.perf_counter() - self.started)

    def done(self, name: str, k: int = 1, keys: tuple[str, ...] = ()) -> dict[str, Any] | None:
        """The facts of round k's finished stage ``name`` (noted as skipped), or None when it has not finished.

        Args:
            name: the stage.
            k: its round.
            keys: facts the caller reads; a marker without them is refused like a truncated one.

        Raises:
            EfficientTrackError: the marker is unreadable, truncated or lacks ``keys``, naming the file and the fix.
        """
        path = self.folder(k) / "stages" / f"{name}.json"
        if not path.exists():
            return None
        try:
            facts = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise _broken_marker(path, name, f"unreadable ({exc})") from exc
        if not isinstance(facts, dict):
            raise _broken_marker(path, name, "not a mapping of facts")
        missing = [key for key in keys if key not in facts]
        if missing:
            raise _broken_marker(path, name, f"missing {', '.join(missing)}")
        self.skipped.append(self.key(name, k))
        self.facts[self.key(name, k)] = facts
        return facts

    def once(self, name: str, compute: Callable[[], dict[str, Any]], k: int = 1, keys: tuple[str, ...] = ()) -> dict[str, Any]:
        """The facts of stage ``name``: read back when finished, else ``compute()``'d and kept (a plan, a tally).

        Args:
            name: the stage.
            compute: makes its facts.
            k: its round.
            keys: facts the caller reads from a finished stage's marker (:meth:`done`).
        """
        facts = self.done(name, k, keys)
        return facts if facts is not None else self._finish(name, k, compute())

    def run(
        self,
        name: str,
        work: Callable[[], tuple[T, dict[str, Any]]],
        load: Callable[[], T],
        k: int = 1,
        keys: tuple[str, ...] = (),
    ) -> tuple[T, dict[str, Any]]:
        """Round k's stage ``name``: ``load()`` what it made when it finished, else do ``work()`` and time it.

        Args:
            name: the stage.
            work: does the stage; returns what it made and its facts.
            load: reads back what a finished stage made.
            k: the round.
            keys: facts the caller reads from a finished stage's marker (:meth:`done`).

        Returns:
            What the stage made, and its facts with ``seconds``: what it took, all of it when a kill split it.
        """
        facts = self.done(name, k, keys)
        if facts is not None:
            return load(), facts
        key = self.key(name, k)
        with self._lock:
            entry = self.work.setdefault(key, {"began": self.seconds_spent(), "invocation": self.invocation})
            self._save()
        began = time.perf_counter()
        value, facts = work()
        seconds = time.perf_counter() - began
        with self._lock:
            if entry["invocation"] != self.invocation:
                seconds = max(seconds, self.seconds_spent() - entry["began"])
            facts = self._finish(name, k, {**facts, "seconds": seconds})
            del self.work[key]
            self._save()
        return value, facts

    @contextlib.contextmanager
    def counting(self) -> Iterator[None]:
        """Keep :data:`SPENT` up to date while the block runs; a block that ends without error finishes the run."""
        stop = threading.Event()

        def beat() -> None:
            while not stop.wait(HEARTBEAT):
                with contextlib.suppress(OSError, EfficientTrackError):  # the next write in the run's thread reports it
                    self._save()

        self._save()
        thread = threading.Thread(target=beat, name="efficienttrack-ledger", daemon=True)
        thread.start()
        try:
            yield
            self.finished = True
        finally:
            stop.set()
            thread.join()
            with contextlib.suppress(OSError, EfficientTrackError):  # an error on its way out is the one to show
                self._save()

    def key(self, name: str, k: int = 1) -> str:
        """How :attr:`skipped` and :attr:`facts` name round k's stage ``name``."""
        return name if k == 1 else f"{ROUNDS}/{k}/{name}"

    def _finish(self, name: str, k: int, facts: dict[str, Any]) -> dict[str, Any]:
        write_json(self.folder(k) / "stages" / f"{name}.json", facts)
        self.facts[self.key(name, k)] = facts
        return facts

    def _save(self) -> None:
        with self._lock:
            facts = {"spent_seconds": self.seconds_spent(), "invocations": self.invocation, "finished": self.finished}
            write_json(self.path, {**facts, "work": self.work})


def _broken_marker(path: Path, name: str, problem: str) -> EfficientTrackError:
    """The error for a stage marker that cannot be used: what is wrong, and how to recover."""
    return EfficientTrackError(
        f"{path}: the marker of finished stage '{name}' is {problem}, truncated or corrupted; delete that file to redo "
        "the stage on the next run, or start afresh with --force"
    )


def read_spent(path: Path) -> tuple[float, int, bool, dict[str, dict[str, Any]]]:
    """The run's time so far, as :data:`SPENT` keeps it; nothing spent when the file does not exist.

    Args:
        path: ``OUT/stages/time_spent.json``.

    Returns:
        The seconds spent, the invocations, whether the last one finished the run, and the stages begun and not finished.

    Raises:
        EfficientTrackError: the file is unreadable or malformed, naming it and the fix.
    """
    if not path.exists():
        return 0.0, 0, False, {}
    try:
        data = json.loads(path.read_text())
        spent, invocations, finished = float(data["spent_seconds"]), data["invocations"], data["finished"]
        work = {str(name): dict(entry) for name, entry in data["work"].items()}
        if not math.isfinite(spent) or spent < 0 or not isinstance(invocations, int) or not isinstance(finished, bool):
            raise ValueError("bad spent_seconds, invocations or finished")
        for entry in work.values():
            if not math.isfinite(float(entry["began"])) or not isinstance(entry["invocation"], int):
                raise ValueError("bad work entry")
    except (OSError, ValueError, TypeError, KeyError, AttributeError) as exc:
        raise EfficientTrackError(
            f"{path}: the ledger's record of the run's time is unreadable ({exc}); delete it to count from the next "
            "invocation only, or start afresh with --force"
        ) from exc
    return spent, invocations, finished, work

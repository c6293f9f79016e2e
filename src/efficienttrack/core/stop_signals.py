"""Stop signals handled as Ctrl-C: SIGTERM and SIGHUP end a machine's run cleanly instead of killing the process.

A supervisor (systemd, Docker, a job scheduler) stops a process with SIGTERM, and a closed terminal or a dropped SSH
session sends SIGHUP. Python's default for both ends the process on the spot: no ``finally`` block runs, so a run on
a machine would neither send the raw reference once more nor close the machine's adapter, and its log would lack
the summary line. Inside :func:`stop_signals_as_interrupt` the first such signal raises :class:`Terminated`, a
:class:`KeyboardInterrupt`, so the code that handles Ctrl-C handles it too; further stop signals are ignored while
that cleanup runs (Ctrl-C and SIGKILL still end the process).
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager

STOP_SIGNALS = tuple(getattr(signal, name) for name in ("SIGTERM", "SIGHUP") if hasattr(signal, name))
"""The signals handled: SIGTERM, and SIGHUP where the platform has it."""


class Terminated(KeyboardInterrupt):
    """A stop signal arrived; caught wherever Ctrl-C (:class:`KeyboardInterrupt`) is.

    Args:
        signum: the signal's number.
    """

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def interrupt_name(exc: KeyboardInterrupt) -> str:
    """What stopped a run: the signal's name (``"SIGTERM"``, ``"SIGHUP"``) for a :class:`Terminated`, else ``"Ctrl-C"``.

    Args:
        exc: the interrupt caught.
    """
    return signal.Signals(exc.signum).name if isinstance(exc, Terminated) else "Ctrl-C"


@contextmanager
def stop_signals_as_interrupt() -> Iterator[None]:
    """Within the block, the first SIGTERM or SIGHUP raises :class:`Terminated`; the handlers before it are restored after.

    Only signals left at their default action are taken: one a program or ``nohup`` set to something else keeps it.
    Signal handlers can only be set in the main thread; elsewhere the block changes nothing.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[int] = []

    def handler(signum: int, frame: object) -> None:
        if not received:
            received.append(signum)
            raise Terminated(signum)

    taken = [s for s in STOP_SIGNALS if signal.getsignal(s) is signal.SIG_DFL]
    previous = {s: signal.signal(s, handler) for s in taken}
    try:
        yield
    finally:
        for s, action in previous.items():
            signal.signal(s, action)

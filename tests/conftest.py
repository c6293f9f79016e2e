import pytest
import torch


@pytest.fixture(autouse=True, scope="session")
def one_thread():
    """Tiny networks run fastest (and reproducibly) on one thread, also on a busy 2-core machine."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture
def interrupt_at(monkeypatch):
    """``interrupt_at(count)``: the baseline runs that follow are killed (KeyboardInterrupt) when they would measure a
    point at ``count`` interaction steps or beyond, as a user's Ctrl-C would; ``monkeypatch.undo()`` ends it."""
    from efficienttrack.baselines.curve import CurveRecorder

    measure = CurveRecorder.measure

    def arm(count):
        def killed(recorder, act, at, *args, **kwargs):
            if at >= count:
                raise KeyboardInterrupt
            measure(recorder, act, at, *args, **kwargs)

        monkeypatch.setattr(CurveRecorder, "measure", killed)

    return arm


@pytest.fixture
def default_stop_signals():
    """SIGTERM and SIGHUP at their default action for the test (Ray's ``init`` leaves a SIGTERM handler in the process)."""
    import signal

    from efficienttrack.core.stop_signals import STOP_SIGNALS

    previous = {s: signal.signal(s, signal.SIG_DFL) for s in STOP_SIGNALS}
    yield
    for s, action in previous.items():
        signal.signal(s, action)

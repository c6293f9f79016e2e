import functools
import os
from pathlib import Path

import pytest
import torch
from matplotlib.figure import Figure

THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS")


@pytest.fixture(autouse=True, scope="session")
def one_thread():
    """Tiny networks run fastest (and reproducibly) on one thread, also on a busy 2-core machine.

    The processes that tests start (commands, study workers, Ray) inherit one thread too: with torch's default of one
    per core they oversubscribe the cores beside the other test worker, and a tiny run takes ten times as long.
    """
    threads = torch.get_num_threads()
    saved = {name: os.environ.get(name) for name in THREAD_VARIABLES}
    torch.set_num_threads(1)
    os.environ.update(dict.fromkeys(THREAD_VARIABLES, "1"))
    yield
    torch.set_num_threads(threads)
    for name, value in saved.items():
        if value is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = value


def pytest_collection_modifyitems(items):
    """Tests marked ``early`` run first: each takes 20 s or more alone, and a parallel run that reaches one last ends on
    one worker while the other waits."""
    items.sort(key=lambda item: item.get_closest_marker("early") is None)


@pytest.fixture(autouse=True, scope="session")
def one_click_command():
    """Typer builds the click command anew from the app at every ``CliRunner().invoke`` (about 65 ms, some 400 times a
    run of the suite): the tests build it once per app. Click commands keep no state between invocations."""
    import typer.main
    import typer.testing

    build = typer.testing._get_command
    typer.testing._get_command = functools.cache(build)
    yield
    typer.testing._get_command = build


UNRENDERED = b"figure built, not rendered: tests/conftest.py"
"""What a figure's file holds in a test not marked ``figures``: it names where it came from, and is no PNG."""
SAVEFIG = Figure.savefig


def _unrendered(figure, target, *args, **kwargs):
    if hasattr(target, "write"):
        target.write(UNRENDERED)
    else:
        Path(target).write_bytes(UNRENDERED)


@pytest.fixture(autouse=True, scope="session")
def unrendered_figures():
    """Figures are built, but rendered to PNG only in tests marked ``figures``, which check what they show.

    Every run and evaluation draws its figures whatever ``--plots`` says, and rendering is about a quarter of the time
    of the tests that train; the tests of other things check that the figures' files are written, not their pixels.
    Session-wide, so that the runs shared by a module's tests are not rendered either.
    """
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(Figure, "savefig", _unrendered)
        yield


@pytest.fixture(autouse=True)
def rendered_when_marked(request, monkeypatch):
    """Tests marked ``figures`` render their figures (:func:`unrendered_figures`)."""
    if request.node.get_closest_marker("figures"):
        monkeypatch.setattr(Figure, "savefig", SAVEFIG)


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


@pytest.fixture(scope="session")
def toy_refs():
    """The toy runs' four training and two test references (``toy_system.toy_split``)."""
    from toy_system import toy_split

    return toy_split()


@pytest.fixture(scope="session")
def toy_run(tmp_path_factory, toy_refs):
    """One finished toy run (the toy system, ``TOY_CFG``, one round), shared by the session: ``(folder, RunResult)``.

    Its folder is for reading: a test that runs the pipeline in it again (resume, more rounds, ``--force``) copies it
    first (``shutil.copytree``).
    """
    from efficienttrack.workflow.pipeline import run_pipeline
    from toy_system import TOY, TOY_CFG

    out = tmp_path_factory.mktemp("toy_run")
    return out, run_pipeline(TOY, *toy_refs, out, TOY_CFG)


@pytest.fixture(scope="session")
def lag_model():
    """The tiny dynamics model trained on ``test_dynamics.lag_records()`` (its ``ModelTrainResult``), shared by the session.

    A test module that hands the model to code which changes it (``train_policy`` freezes it) takes a deep copy.
    """
    from test_dynamics import lag_records, train_tiny_model

    return train_tiny_model(lag_records())

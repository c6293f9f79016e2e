"""Stop signals as Ctrl-C (efficienttrack.core.stop_signals): taken only when at their default, once, and given back."""

import os
import signal
import threading

import pytest

from efficienttrack.core.stop_signals import Terminated, interrupt_name, stop_signals_as_interrupt


def test_the_first_sigterm_raises_a_keyboard_interrupt_and_later_ones_are_ignored(default_stop_signals):
    with stop_signals_as_interrupt():
        assert signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL  # else the kill below ends the test run
        with pytest.raises(KeyboardInterrupt) as caught:
            os.kill(os.getpid(), signal.SIGTERM)
        assert isinstance(caught.value, Terminated) and interrupt_name(caught.value) == "SIGTERM"
        try:
            os.kill(os.getpid(), signal.SIGTERM)  # during the cleanup: ignored
        except KeyboardInterrupt:
            pytest.fail("a second SIGTERM interrupted the cleanup")
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL


def test_a_signal_set_by_the_program_or_nohup_is_left_alone(default_stop_signals):
    def own(signum, frame):
        pass

    previous = signal.signal(signal.SIGHUP, signal.SIG_IGN), signal.signal(signal.SIGTERM, own)
    try:
        with stop_signals_as_interrupt():
            assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN and signal.getsignal(signal.SIGTERM) is own
    finally:
        signal.signal(signal.SIGHUP, previous[0])
        signal.signal(signal.SIGTERM, previous[1])


def test_outside_the_main_thread_nothing_changes(default_stop_signals):
    seen = []

    def body():
        with stop_signals_as_interrupt():
            seen.append(signal.getsignal(signal.SIGTERM))

    thread = threading.Thread(target=body)
    thread.start()
    thread.join()
    assert seen == [signal.SIG_DFL]


def test_ctrl_c_is_named_as_such():
    assert interrupt_name(KeyboardInterrupt()) == "Ctrl-C"


@pytest.mark.parametrize(("interrupt", "name"), [(KeyboardInterrupt(), "Ctrl-C"), (Terminated(signal.SIGTERM), "SIGTERM")])
def test_a_command_stopped_says_what_it_kept_and_how_to_go_on(interrupt, name, tmp_path, monkeypatch, capsys):
    import sys

    from efficienttrack import cli
    from efficienttrack.workflow import pipeline

    def stopped(*args, **kwargs):
        raise interrupt

    monkeypatch.setattr(pipeline, "demo", stopped)
    monkeypatch.setattr(sys, "argv", ["efficienttrack", "demo", "--out", str(tmp_path / "d"), "--preset", "tiny"])
    with pytest.raises(SystemExit) as exit_info:
        cli.main()
    assert exit_info.value.code == 130
    assert f"{name}: stopped; what finished is kept in {tmp_path / 'd'}: rerun the same command" in capsys.readouterr().err

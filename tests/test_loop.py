"""The fixed-rate loop (efficienttrack.deploy.loop) against the toy simulator and fault-injecting adapters, on a fake clock."""

import json
import math
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from efficienttrack.cli import app
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.data.records import load_records
from efficienttrack.data.references import Reference, load_references, save_references
from efficienttrack.deploy.deployment import deploy, load_machine, records_from_log
from efficienttrack.deploy.loop import Loop, LoopConfig, Reading, TickLog
from efficienttrack.deploy.machine import SimulatedClock, SimulatedMachine
from efficienttrack.deploy.runtime import Runtime, track
from efficienttrack.learn.policy import AdjustmentPolicy, save_policy
from efficienttrack.learn.settings import POLICY_PRESETS
from efficienttrack.systems.limits import DEFAULT_LIMITS
from efficienttrack.systems.protocol import BatchedSystem
from test_runtime import LinearPolicy
from toy_system import make, sine_refs

DT = 0.05
SRC = Path(__file__).resolve().parents[1] / "src"
RATE = np.asarray(DEFAULT_LIMITS.max_adjust_rate)


class FakeClock(SimulatedClock):
    """Simulated time that also records the sleeps; adapters ``advance`` it to take time."""

    def __init__(self):
        super().__init__(100.0)
        self.sleeps = []

    def sleep(self, seconds):
        self.sleeps.append(seconds)
        super().sleep(seconds)

    def advance(self, seconds):
        self.t += seconds


class FaultyMachine(SimulatedMachine):
    """The toy system with faults per tick k (read call k; call 0 is the start's reading).

    slow_read/slow_send: seconds a read/send takes; old: stamps that many s in the past; nan/drop/raise_read: ticks
    whose reading is NaN, None, or raises; raise_send: tick whose send raises; clamp: the machine clamps the boom;
    interrupt: the tick whose read is cut by Ctrl-C; stop_signal: (tick, signal) sent to this process at that read.
    """

    def __init__(
        self,
        q0,
        clock,
        slow_read=None,
        slow_send=0.0,
        old=None,
        nan=(),
        drop=(),
        raise_read=(),
        raise_send=None,
        clamp=None,
        interrupt=None,
        stop_signal=None,
    ):
        super().__init__(BatchedSystem(make()), q0, clock)
        self.slow_read = slow_read or (lambda k: 0.0)
        self.old = old or (lambda k: 0.0)
        self.slow_send, self.nan, self.drop, self.raise_read = slow_send, set(nan), set(drop), set(raise_read)
        self.raise_send, self.clamp, self.interrupt, self.stop_signal = raise_send, clamp, interrupt, stop_signal
        self.reads, self.sent, self.opened, self.closed = 0, [], 0, 0

    def __enter__(self):
        self.opened += 1
        return super().__enter__()

    def __exit__(self, *exc):
        self.closed += 1
        super().__exit__(*exc)

    def read(self):
        k, self.reads = self.reads, self.reads + 1
        self.clock.advance(self.slow_read(k))
        if k == self.interrupt:
            raise KeyboardInterrupt
        if self.stop_signal is not None and k == self.stop_signal[0]:
            # without a handler the signal would end the test run: fail instead
            assert signal.getsignal(self.stop_signal[1]) is not signal.SIG_DFL, "the loop does not handle the signal"
            os.kill(os.getpid(), self.stop_signal[1])
        if k in self.raise_read:
            raise OSError("CAN bus error")
        if k in self.drop:
            return None
        obs, stamp = super().read()
        if k in self.nan:
            obs[2] = np.nan
        return Reading(obs, stamp - self.old(k))

    def send(self, q_ref):
        if len(self.sent) == self.raise_send:
            raise OSError("CAN bus error")
        self.clock.advance(self.slow_send)
        taken = super().send(q_ref)
        if self.clamp is not None:
            taken = taken.copy()
            taken[0] = min(taken[0], self.clamp)
        self.sent.append(taken)
        return taken


@pytest.fixture
def ref():
    return sine_refs([60], seed=2)[0]


def run(ref, tmp_path, shadow=False, cfg=None, policy=True, **faults):
    clock = FakeClock()
    machine = FaultyMachine(ref.q[0], clock, **faults)
    runtime = Runtime(LinearPolicy(horizon=3) if policy else None, limits=None)
    with TickLog(tmp_path / "log.jsonl", fsync_every=7) as log:
        result = Loop(runtime, machine, DEFAULT_LIMITS, cfg, clock, log, shadow=shadow).run(ref.q, ref.name)
    lines = [json.loads(line) for line in (tmp_path / "log.jsonl").read_text().splitlines()]
    return result, machine, lines[:-1], lines[-1], clock


def adjustment(machine, ref, ticks):
    return np.array(machine.sent) - ref.q[1 : ticks + 1]


def test_shadow_mode_sends_the_raw_reference_and_logs_the_adjustment(ref, tmp_path):
    result, machine, ticks, end, _ = run(ref, tmp_path, shadow=True)
    assert result.reason == "done" and result.ticks == len(ref.q) - 1 == len(ticks) == len(machine.sent)
    np.testing.assert_array_equal(np.array(machine.sent), ref.q[1:])
    logged = np.array([t["a"] for t in ticks])
    assert np.abs(logged[1:]).max() > 0.01  # the policy's adjustment is computed and logged
    assert all("shadow" in t["events"] for t in ticks) and np.all(np.array([t["a_sent"] for t in ticks]) == 0)
    assert end["event"] == "end" and end["reason"] == "done" and end["shadow"] == len(ticks)
    assert machine.opened == machine.closed == 1
    for key in ("tick", "t", "lateness", "compute", "work", "age", "missed", "events", "guard", "obs", "q_des", "q_ref"):
        assert key in ticks[0]


def test_shadow_run_follows_the_same_path_as_the_controller_alone(ref, tmp_path):
    """The loop's shadow run on the simulator equals Algorithm 2 without a policy (the fast path) on the same reference."""
    _, _, ticks, _, _ = run(ref, tmp_path, shadow=True)
    record = track(BatchedSystem(make()), None, [ref], progress=False)[0]
    np.testing.assert_array_equal(np.array([t["obs"][:4] for t in ticks]), record.q)


def test_a_shadow_runs_records_are_those_of_the_controller_alone(ref, tmp_path):
    run(ref, tmp_path, shadow=True)
    [from_log] = records_from_log(tmp_path / "log.jsonl", shadow=True)
    record = track(BatchedSystem(make()), None, [ref], progress=False)[0]
    for name in ("q", "qd", "q_ref", "q_des", "t"):
        np.testing.assert_allclose(getattr(from_log, name), getattr(record, name), atol=1e-12, err_msg=name)
    assert from_log.meta == {
        "name": "log", "reference": "log", "source": "deploy", "first_tick": 0, "shadow": True, "guard": {}, "loop_events": {}
    }  # fmt: skip


def test_records_from_a_log_leave_out_missing_stale_and_skipped_ticks(ref, tmp_path):
    _, machine, ticks, _, _ = run(ref, tmp_path, drop={10}, nan={20}, old=lambda k: 0.2 if k == 30 else 0.0)
    records = records_from_log(tmp_path / "log.jsonl")
    assert [r.meta["name"] for r in records] == ["log", "log-2", "log-3", "log-4"]
    assert [(r.meta["first_tick"], len(r)) for r in records] == [(0, 10), (11, 9), (21, 9), (31, len(ticks) - 31)]
    np.testing.assert_array_equal(records[1].q_ref, np.array([t["q_ref"] for t in ticks[11:20]]))
    np.testing.assert_array_equal(records[3].q[0], ticks[31]["obs"][:4])
    # whole periods lost: the ticks after the gap start a new record
    (tmp_path / "gap").mkdir()
    _, _, ticks, _, _ = run(ref, tmp_path / "gap", slow_read=lambda k: 0.12 if k == 15 else 0.0)
    records = records_from_log(tmp_path / "gap" / "log.jsonl")
    assert ticks[15]["missed"] == 0 and ticks[16]["missed"] > 0
    assert [(r.meta["first_tick"], len(r)) for r in records] == [(0, 16), (ticks[16]["tick"], len(ticks) - 16)]


def test_records_from_a_cut_log_and_a_damaged_one(ref, tmp_path):
    run(ref, tmp_path)
    lines = (tmp_path / "log.jsonl").read_text().splitlines()
    (tmp_path / "cut.jsonl").write_text("\n".join(lines[:25]) + "\n" + lines[25][:40])  # a crash mid-line
    assert [len(r) for r in records_from_log(tmp_path / "cut.jsonl")] == [25]
    (tmp_path / "bad.jsonl").write_text("\n".join([*lines[:5], "{oops", *lines[6:]]))
    with pytest.raises(EfficientTrackError, match="bad.jsonl: line 6 is not JSON"):
        records_from_log(tmp_path / "bad.jsonl")
    (tmp_path / "other.jsonl").write_text('{"step": 1}\n')
    with pytest.raises(EfficientTrackError, match="line 1 has no tick, t, events, obs, q_ref, q_des"):
        records_from_log(tmp_path / "other.jsonl")
    (tmp_path / "list.jsonl").write_text("[1, 2]\n")
    with pytest.raises(EfficientTrackError, match="list.jsonl: line 1 is not a JSON object"):
        records_from_log(tmp_path / "list.jsonl")
    short = json.loads(lines[3]) | {"q_ref": [0.1, 0.2]}
    (tmp_path / "short.jsonl").write_text("\n".join([*lines[:3], json.dumps(short), *lines[4:]]))
    with pytest.raises(EfficientTrackError, match="short.jsonl: line 4: field 'q_ref' must be 4 numbers"):
        records_from_log(tmp_path / "short.jsonl")


def test_armed_run_starts_and_ends_with_a_zero_and_never_jumps(ref, tmp_path):
    result, machine, ticks, _, _ = run(ref, tmp_path)
    a = adjustment(machine, ref, result.ticks)
    np.testing.assert_array_equal(a[0], 0.0)  # the first reference sent is raw
    np.testing.assert_array_equal(a[-1], 0.0)  # and the last
    assert np.abs(a).max() > 0.05  # in between, the policy adjusts
    assert np.all(np.abs(np.diff(a, axis=0)) <= RATE + 1e-12)  # ramps up and down within the rate
    assert ticks[-1]["events"] == ["ramped"] and ticks[0]["events"] == ["start"]


def test_the_policy_sees_the_references_really_sent(ref, tmp_path):
    """In shadow mode the runtime's reference history holds the raw references (sent_instead), as in training."""
    seen = []

    class Spy(LinearPolicy):
        def forward(self, obs_hist, qref_hist, qdes_future):
            seen.append(qref_hist[0, -1].double().numpy().copy())
            return super().forward(obs_hist, qref_hist, qdes_future)

    clock = FakeClock()
    machine = FaultyMachine(ref.q[0], clock)
    Loop(Runtime(Spy(horizon=3), limits=None), machine, DEFAULT_LIMITS, clock=clock, shadow=True).run(ref.q, ref.name)
    np.testing.assert_allclose(np.array(seen[1:]), ref.q[1:-1], atol=1e-6)


def test_deadlines_are_absolute_and_do_not_drift(ref, tmp_path):
    rng = np.random.default_rng(0)
    work = rng.uniform(0.0, 0.04, 200)
    _, _, ticks, end, clock = run(ref, tmp_path, slow_read=lambda k: work[k])
    np.testing.assert_allclose([t["t"] for t in ticks], np.arange(len(ticks)) * DT, atol=1e-9)
    assert "overrun" not in end and end["lateness_ms"]["max"] < 1e-6
    # the start's read took work[0]; the last tick starts (n − 1)·dt after that, and its read takes work[n − 1]
    assert clock.t - 100.0 == pytest.approx(work[0] + (len(ticks) - 1) * DT + work[len(ticks) - 1], abs=1e-9)


def test_slow_adapter_overruns_hold_a_zero_then_stop(ref, tmp_path):
    cfg = LoopConfig(hold_after=3, stop_after=6)
    result, machine, ticks, end, _ = run(ref, tmp_path, cfg=cfg, slow_read=lambda k: 0.01 if k < 10 else 0.06)
    assert result.reason == "overruns" and end["reason"] == "overruns" and end["error"] == "6 overruns in a row"
    events = [t["events"] for t in ticks]
    assert ["overrun" in e for e in events[10:]] == [False] + [True] * 6
    assert ["hold" in e for e in events[10:]] == [False] * 3 + [True] * 4
    a = np.array([t["q_ref"] for t in ticks]) - np.array([t["q_des"] for t in ticks])
    np.testing.assert_array_equal(a[-4:], 0.0)  # held, and the stop's reference is raw
    assert np.abs(a[5:10]).max() > 0 and result.ticks == len(machine.sent) == 17


def test_a_single_overrun_is_counted_and_whole_periods_lost_are_skipped(ref, tmp_path):
    result, machine, ticks, end, _ = run(ref, tmp_path, slow_read=lambda k: 0.13 if k == 5 else 0.0)
    assert result.reason == "done" and end["overrun"] == 1 and end["missed_ticks"] == 1
    late = ticks[6]  # tick 5 ended 0.13 s after its deadline: tick 6 is skipped, tick 7 runs 0.03 s late
    assert late["tick"] == 7 and late["missed"] == 1 and late["lateness"] == pytest.approx(0.03)
    np.testing.assert_array_equal(late["q_des"], ref.q[8])  # the reference follows the clock
    assert len(machine.sent) == result.ticks == len(ref.q) - 2  # the reference follows the clock
    assert "hold" not in end


def test_stale_readings_send_raw_and_a_silent_sensor_stops(ref, tmp_path):
    cfg = LoopConfig(stale_ticks=2, stop_stale_ticks=6)
    old = lambda k: 0.12 if 10 <= k < 13 else (0.31 if k >= 20 else 0.0)  # noqa: E731
    result, machine, ticks, end, _ = run(ref, tmp_path, cfg=cfg, old=old)
    a = adjustment(machine, ref, result.ticks)
    assert [("stale" in t["events"]) for t in ticks[9:14]] == [False, True, True, True, False]
    np.testing.assert_array_equal(a[10:13], 0.0)
    assert np.abs(a[13]).max() > 0
    assert result.reason == "stale_sensor" and result.ticks == 21 and end["error"] == "last good reading 310 ms old"
    np.testing.assert_array_equal(a[-1], 0.0)


def test_nan_readings_fall_back_and_are_logged_as_null(ref, tmp_path):
    result, machine, ticks, end, _ = run(ref, tmp_path, nan=(7,))
    assert result.reason == "done" and end["nonfinite"] == 1
    assert ticks[7]["obs"][2] is None and "obs_nonfinite" in ticks[7]["guard"] and "nonfinite" in ticks[7]["events"]
    np.testing.assert_array_equal(adjustment(machine, ref, result.ticks)[7], 0.0)


def test_dropped_samples_send_raw_and_a_dead_sensor_stops(ref, tmp_path):
    result, machine, ticks, end, _ = run(ref, tmp_path, drop={4, *range(30, 100)})
    assert "dropped" in ticks[4]["events"] and end["dropped"] == 1 + 11
    a = adjustment(machine, ref, result.ticks)
    np.testing.assert_array_equal(a[4], 0.0)
    np.testing.assert_array_equal(a[30:], 0.0)
    assert result.reason == "stale_sensor" and result.ticks == 41  # 10 periods after the last good reading (tick 29)


def test_raising_read_sends_raw_once_stops_and_closes(ref, tmp_path):
    result, machine, ticks, end, _ = run(ref, tmp_path, raise_read={12})
    assert result.reason == "read_error" and end["error"] == "OSError: CAN bus error"
    assert result.ticks == len(machine.sent) == 13 and machine.closed == 1
    np.testing.assert_array_equal(adjustment(machine, ref, 13)[12], 0.0)


def test_raising_send_stops_at_once_and_closes(ref, tmp_path):
    result, machine, ticks, end, _ = run(ref, tmp_path, raise_send=9)
    assert result.reason == "send_error" and len(machine.sent) == 9 and len(ticks) == 9 and machine.closed == 1


def test_a_raising_runtime_sends_raw_and_stops(ref, tmp_path):
    class Failing(Runtime):
        def step(self, obs, q_des_future):
            if self.steps == 6:
                raise RuntimeError("boom")
            return super().step(obs, q_des_future)

    clock = FakeClock()
    machine = FaultyMachine(ref.q[0], clock)
    result = Loop(Failing(LinearPolicy(horizon=3), limits=None), machine, DEFAULT_LIMITS, clock=clock).run(ref.q, ref.name)
    assert result.reason == "runtime_error" and result.error == "RuntimeError: boom" and result.ticks == 7
    np.testing.assert_array_equal(adjustment(machine, ref, 7)[6], 0.0)


def test_ctrl_c_sends_raw_and_ends_the_log(ref, tmp_path):
    result, machine, ticks, end, _ = run(ref, tmp_path, interrupt=8)
    assert result.reason == end["reason"] == "interrupted" and machine.closed == 1
    np.testing.assert_array_equal(machine.sent[-1], ref.q[9])


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP])
def test_a_stop_signal_sends_raw_closes_and_ends_the_log_like_ctrl_c(ref, tmp_path, signum, default_stop_signals):
    result, machine, ticks, end, _ = run(ref, tmp_path, stop_signal=(8, signum))
    assert result.reason == end["reason"] == "interrupted" and end["error"] == signal.Signals(signum).name
    assert machine.closed == 1 and len(ticks) == 8
    np.testing.assert_array_equal(machine.sent[-1], ref.q[9])
    assert signal.getsignal(signum) is signal.SIG_DFL  # the handler lasts the run only


def test_a_machine_that_clamps_is_logged_and_the_history_follows(ref, tmp_path):
    result, machine, ticks, end, _ = run(ref, tmp_path, clamp=ref.q[:, 0].min() + 0.05)
    assert end["send_changed"] > 0 and result.reason == "done"
    np.testing.assert_array_equal([t["q_ref"] for t in ticks], np.array(machine.sent))
    [record] = records_from_log(tmp_path / "log.jsonl")  # the record says at which rows the machine clamped
    changed = [t["tick"] for t in ticks if "send_changed" in t["events"]]
    assert record.meta["loop_events"]["send_changed"] == changed and len(changed) == end["send_changed"]


@pytest.mark.parametrize(
    ("faults", "message"),
    [
        ({"drop": {0}}, "no finite first reading"),
        ({"nan": {0}}, "no finite first reading"),
        ({"raise_read": {0}}, "first read failed"),
        ({"old": lambda k: 1.0}, "1000 ms old"),
    ],
)
def test_an_unsafe_start_sends_nothing(ref, tmp_path, faults, message):
    with pytest.raises(EfficientTrackError, match=message):
        run(ref, tmp_path, **faults)


def test_a_machine_away_from_the_start_sends_nothing(ref):
    clock = FakeClock()
    machine = FaultyMachine(ref.q[0] + np.array([0, 0.3, 0, 0]), clock)
    with pytest.raises(EfficientTrackError, match="0.300 rad from the reference's first position"):
        Loop(Runtime(None, limits=None), machine, DEFAULT_LIMITS, clock=clock).run(ref.q, ref.name)
    assert machine.sent == [] and machine.closed == 1


def test_log_is_flushed_per_line_fsynced_every_n_and_never_overwritten(tmp_path, monkeypatch):
    synced = []
    monkeypatch.setattr("efficienttrack.deploy.loop.os.fsync", lambda fd: synced.append(fd))
    path = tmp_path / "x.jsonl"
    with TickLog(path, fsync_every=3) as log:
        for i in range(7):
            log.write({"i": i, "v": np.float64(math.nan), "a": np.arange(2)})
            assert len(path.read_text().splitlines()) == i + 1  # on disk (flushed) before the next tick
        assert len(synced) == 2
    assert len(synced) == 3
    assert json.loads(path.read_text().splitlines()[0]) == {"i": 0, "v": None, "a": [0, 1]}
    with pytest.raises(EfficientTrackError, match="exists already"), TickLog(path):
        pass


def test_loop_config_refuses_settings_that_cannot_work():
    for bad in ({"dt": 0}, {"hold_after": 0}, {"stop_after": 2, "hold_after": 3}, {"stale_ticks": 5, "stop_stale_ticks": 2}):
        with pytest.raises(EfficientTrackError, match="loop:"):
            LoopConfig(**bad)


def test_runtime_sent_instead_replaces_the_last_reference():
    runtime = Runtime(LinearPolicy(horizon=2), limits=None)
    runtime.start(np.zeros((1, 8)))
    with pytest.raises(EfficientTrackError, match="before a step"):
        runtime.sent_instead(np.zeros((1, 4)))
    runtime.step(np.zeros((1, 8)), np.full((1, 2, 4), 0.1))
    runtime.sent_instead(np.full((1, 4), 0.1))
    np.testing.assert_array_equal(runtime._history.q_ref[0, -1], 0.1)
    with pytest.raises(EfficientTrackError, match="finite q_ref of shape"):
        runtime.sent_instead(np.full((1, 3), 0.1))


def test_deploy_runs_references_in_turn_and_stops_after_a_stopped_run(tmp_path):
    refs = sine_refs([30, 40, 35], seed=5)
    clock = FakeClock()
    machines = []

    def make_machine(ref):
        machines.append(FaultyMachine(ref.q[0], clock, raise_read={5} if len(machines) == 1 else ()))
        return machines[-1]

    results = deploy(
        refs, Runtime(None, limits=None), make_machine, DEFAULT_LIMITS, tmp_path / "out", clock=clock, shadow=True
    )
    assert [r.reason for r in results] == ["done", "read_error"] and len(machines) == 2
    summary = json.loads((tmp_path / "out" / "deploy.json").read_text())
    assert [r["name"] for r in summary["runs"]] == ["ref_00", "ref_01"] and summary["shadow"] is True
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["deploy.json", "records", "ref_00.jsonl", "ref_01.jsonl"]
    records = load_records(tmp_path / "out" / "records")  # the stopped run's ticks before the failed read too
    assert [(r.meta["name"], len(r), r.meta["shadow"]) for r in records] == [("ref_00", 29, True), ("ref_01", 5, True)]


def test_a_rerun_resumes_at_the_stopped_run_and_keeps_the_earlier_try(tmp_path):
    refs = sine_refs([30, 40, 35], seed=5)
    clock, opened = FakeClock(), []

    def make_machine(ref, faults=None):
        opened.append(ref.name)
        return FaultyMachine(ref.q[0], clock, **(faults or {}).get(ref.name, {}))

    def run_deploy(faults=None, shadow=True):
        machine = lambda ref: make_machine(ref, faults)  # noqa: E731
        return deploy(refs, Runtime(None, limits=None), machine, DEFAULT_LIMITS, tmp_path / "out", clock=clock, shadow=shadow)

    assert [r.reason for r in run_deploy({"ref_01": {"raise_read": {5}}})] == ["done", "read_error"]
    opened.clear()
    assert [r.reason for r in run_deploy()] == ["done", "done"] and opened == ["ref_01", "ref_02"]
    out = tmp_path / "out"
    summary = json.loads((out / "deploy.json").read_text())
    assert [(r["name"], r["reason"]) for r in summary["runs"]] == [("ref_00", "done"), ("ref_01", "done"), ("ref_02", "done")]
    assert (out / "ref_01.stopped-1.jsonl").exists()  # the stopped try's log, and its records by that name
    records = {r.meta["name"]: len(r) for r in load_records(out / "records")}
    assert records == {"ref_00": 29, "ref_01.stopped-1": 5, "ref_01": 39, "ref_02": 34}
    opened.clear()
    assert run_deploy() == [] and opened == []  # all done: nothing is sent
    with pytest.raises(EfficientTrackError, match=r"deploy.json: a deployment with other settings \(shadow: true here, false"):
        run_deploy(shadow=False)


def test_a_run_too_short_for_a_record_warns(tmp_path):
    clock = FakeClock()
    refs = sine_refs([30], seed=5)
    with pytest.warns(UserWarning, match="no episode records from ref_00.jsonl: no two usable ticks in a row"):
        deploy(refs, Runtime(None, limits=None), lambda ref: FaultyMachine(ref.q[0], clock, raise_read={1}), DEFAULT_LIMITS,
               tmp_path / "out", clock=clock)  # fmt: skip
    assert not (tmp_path / "out" / "records").exists()


def test_load_machine_names_a_missing_adapter_method():
    with pytest.raises(EfficientTrackError, match="the adapter has no __enter__, __exit__, read, send"):
        load_machine("toy_system:make", {})(sine_refs([5])[0])


# ------------------------------------------------------------------------------------------------ the command


def invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args], env={"COLUMNS": "200"})


class DyingMachine(SimulatedMachine):
    """A user's adapter (``--machine test_loop:DyingMachine``): the toy system at rest, whose sensor dies after 2 reads."""

    def __init__(self):
        super().__init__(BatchedSystem(make()), np.zeros(4))
        self.reads = 0

    def read(self):
        self.reads += 1
        return super().read() if self.reads <= 2 else None


@pytest.fixture
def deploy_inputs(tmp_path):
    """Two short generated xe75 references and an untrained tiny policy."""
    assert invoke("refs", "generate", "--out", tmp_path / "gen", "--n", "2").exit_code == 0
    refs = [Reference(r.name, r.q[:40]) for r in load_references(tmp_path / "gen")]
    save_references(refs, tmp_path / "refs")
    policy = AdjustmentPolicy(POLICY_PRESETS["tiny"])
    torch.nn.init.normal_(policy.pi_phi.body[-1].weight, std=0.5)
    save_policy(policy, tmp_path / "policy.pt")
    return tmp_path / "refs", tmp_path / "policy.pt"


def test_deploy_refuses_to_send_without_arm(deploy_inputs, tmp_path):
    refs, policy = deploy_inputs
    for extra in ((), ("--shadow",)):
        result = invoke("deploy", "--refs", refs, "--policy", policy, "--out", tmp_path / "o", "--fast", *extra)
        assert isinstance(result.exception, EfficientTrackError) and "add --arm to allow motion" in str(result.exception)
    assert not (tmp_path / "o").exists()


def test_deploy_on_the_simulator_in_shadow_mode_then_armed(deploy_inputs, tmp_path):
    refs, policy = deploy_inputs
    shadow = invoke("deploy", "--refs", refs, "--policy", policy, "--out", tmp_path / "s", "--fast", "--arm", "--shadow")
    assert shadow.exit_code == 0, shadow.output
    assert "ref_01: done, 39 ticks" in shadow.output and "2 run(s) done (shadow)" in shadow.output
    lines = [json.loads(x) for x in (tmp_path / "s" / "ref_02.jsonl").read_text().splitlines()]
    assert np.abs([t["a"] for t in lines[1:-1]]).max() > 0 and np.all(np.array([t["a_sent"] for t in lines[:-1]]) == 0)
    armed = invoke("deploy", "--refs", refs, "--policy", policy, "--out", tmp_path / "a", "--fast", "--arm")
    assert armed.exit_code == 0, armed.output
    a_sent = np.array([json.loads(x)["a_sent"] for x in (tmp_path / "a" / "ref_01.jsonl").read_text().splitlines()[:-1]])
    assert np.abs(a_sent).max() > 0 and not a_sent[0].any() and not a_sent[-1].any()
    summary = json.loads((tmp_path / "a" / "deploy.json").read_text())
    assert summary["shadow"] is False and [r["reason"] for r in summary["runs"]] == ["done", "done"]
    again = invoke("deploy", "--refs", refs, "--out", tmp_path / "a", "--fast", "--arm")
    assert isinstance(again.exception, EfficientTrackError)  # a finished deployment's logs are not overwritten


def test_convert_makes_a_deploy_log_into_the_records_deploy_wrote(deploy_inputs, tmp_path):
    refs, policy = deploy_inputs
    args = ("deploy", "--refs", refs, "--policy", policy, "--out", tmp_path / "a", "--fast", "--arm", "--accept-worse")
    assert invoke(*args).exit_code == 0  # an unproven policy: never evaluated, never run in shadow mode here
    result = invoke("convert", tmp_path / "a" / "ref_01.jsonl", "--out", tmp_path / "c")
    assert result.exit_code == 0 and "wrote 1 episode(s)" in result.output, result.output
    [converted], [written] = load_records(tmp_path / "c"), load_records(tmp_path / "a" / "records" / "ref_01.npz")
    for name in ("q", "qd", "q_ref", "q_des", "t"):
        np.testing.assert_array_equal(getattr(converted, name), getattr(written, name))
    (tmp_path / "short.jsonl").write_text("\n".join((tmp_path / "a" / "ref_01.jsonl").read_text().splitlines()[:1]))
    result = invoke("convert", tmp_path / "short.jsonl", "--out", tmp_path / "c2")
    assert "short.jsonl: no episode records in this tick log" in str(result.exception)


def test_deploy_a_machine_needs_its_limits_and_real_time(deploy_inputs, tmp_path):
    refs, _ = deploy_inputs
    result = invoke("deploy", "--refs", refs, "--out", tmp_path / "o", "--arm", "--machine", "test_loop:DyingMachine")
    assert "--machine needs --limits FILE" in str(result.exception)
    (tmp_path / "lim.json").write_text("{}")
    args = ("deploy", "--refs", refs, "--out", tmp_path / "o", "--arm", "--machine", "test_loop:DyingMachine")
    result = invoke(*args, "--limits", tmp_path / "lim.json", "--fast")
    assert "--fast runs on a simulated clock, which a real machine does not keep" in str(result.exception)


def test_deploy_exits_1_when_a_watchdog_stops_a_run(tmp_path):
    save_references([Reference("rest", np.zeros((40, 4)))], tmp_path / "refs")
    (tmp_path / "lim.json").write_text("{}")
    result = invoke(
        "deploy", "--refs", tmp_path / "refs", "--out", tmp_path / "o", "--arm", "--machine", "test_loop:DyingMachine",
        "--limits", tmp_path / "lim.json", "--stale-ticks", "1", "--stop-stale-ticks", "2",
    )  # fmt: skip
    assert result.exit_code == 1 and "rest: stale_sensor" in result.output
    end = json.loads((tmp_path / "o" / "rest.jsonl").read_text().splitlines()[-1])
    assert end["reason"] == "stale_sensor" and end["ticks"] <= 5


DEPLOY_WITHOUT_TORCH = """
import json
from efficienttrack.deploy.deployment import deploy, machine_parts, policy_runtime
from efficienttrack.data.references import load_references
from efficienttrack.systems.spec import SystemSpec

export, refs, out = sys.argv[1:4]
make_machine, limits, clock = machine_parts(SystemSpec(), None, {}, True)
runtime = policy_runtime(export, limits, "cpu")
results = deploy(load_references(refs), runtime, make_machine, limits, out, clock=clock, shadow=True)
print(json.dumps([r.reason for r in results]))
assert "torch" not in sys.modules, "deploying an export imported torch"
"""


def test_deploy_runs_an_export_folder_in_onnx_runtime(deploy_inputs, tmp_path):
    from efficienttrack.deploy.export import export_policy
    from efficienttrack.learn.policy import load_policy
    from test_export import BLOCK_TORCH

    refs, policy = deploy_inputs
    export = export_policy(load_policy(policy), tmp_path / "export")
    runs = {}
    for name, given in (("pt", policy), ("onnx", export)):
        result = invoke("deploy", "--refs", refs, "--policy", given, "--out", tmp_path / name, "--fast", "--arm", "--shadow")
        assert result.exit_code == 0, result.output
        runs[name] = [json.loads(x) for x in (tmp_path / name / "ref_01.jsonl").read_text().splitlines()[:-1]]
    a_pt, a_onnx = (np.array([tick["a"] for tick in runs[name]]) for name in ("pt", "onnx"))
    assert np.abs(a_pt).max() > 0.01  # the policy adjusts; shadow mode sends the raw reference, so both runs see the same
    np.testing.assert_allclose(a_onnx, a_pt, rtol=0, atol=1e-5)
    assert json.loads((tmp_path / "onnx" / "deploy.json").read_text())["policy"] == str(export)
    # on a machine without torch: the export through the library's deploy
    script = tmp_path / "deploy.py"
    script.write_text(BLOCK_TORCH + DEPLOY_WITHOUT_TORCH)
    env = {**os.environ, "PYTHONPATH": str(SRC)}
    args = [sys.executable, str(script), str(export), str(refs), str(tmp_path / "no_torch")]
    done = subprocess.run(args, capture_output=True, text=True, env=env, timeout=120)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout.splitlines()[-1]) == ["done", "done"]


def test_deploy_refuses_a_damaged_export_folder(deploy_inputs, tmp_path):
    refs, _ = deploy_inputs
    (tmp_path / "export").mkdir()
    result = invoke("deploy", "--refs", refs, "--policy", tmp_path / "export", "--out", tmp_path / "o", "--fast", "--arm")
    assert isinstance(result.exception, EfficientTrackError) and "policy.json: no such file" in str(result.exception)
    from efficienttrack.deploy.export import export_policy
    from efficienttrack.learn.policy import load_policy

    export = export_policy(load_policy(deploy_inputs[1]), tmp_path / "slow")
    contract = json.loads((export / "policy.json").read_text())
    (export / "policy.json").write_text(json.dumps({**contract, "dt": 0.1}))
    result = invoke("deploy", "--refs", refs, "--policy", export, "--out", tmp_path / "o", "--fast", "--arm")
    assert isinstance(result.exception, EfficientTrackError) and "made for dt = 0.1 s" in str(result.exception)

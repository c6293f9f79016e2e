"""Sensor faults (efficienttrack.deploy.sensor): impossible readings are found, and they stop an armed run within ticks."""

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.data.references import Reference, save_references
from efficienttrack.deploy.loop import Loop, Reading, TickLog
from efficienttrack.deploy.machine import SimulatedMachine
from efficienttrack.deploy.runtime import Runtime
from efficienttrack.deploy.sensor import first_sensor_fault
from efficienttrack.systems.limits import DEFAULT_LIMITS, GuardLimits, limits_preset_path
from efficienttrack.systems.protocol import BatchedSystem
from test_loop import FakeClock, invoke
from test_runtime import LinearPolicy
from toy_system import make, sine_refs

REAL_LOGS = Path(__file__).resolve().parents[2] / "shared" / "data" / "xe75"
LIMITS = GuardLimits(q_min=(-0.5, -1.0, -0.5, -math.pi), q_max=(0.6, 0.5, 2.3, math.pi), max_speed=(1.0, 2.0, 3.0, 1.5))
FAULT_TICK = 21


def readings(q, qd, dt=0.05):
    """(T, 8) observations and (T,) stamps from positions and velocities."""
    q, qd = np.atleast_2d(q), np.atleast_2d(qd)
    return np.concatenate([q, qd], axis=1), np.arange(len(q)) * dt


def test_consistent_readings_are_no_fault_and_each_kind_names_joint_value_and_limit():
    qd = np.array([[0.0, 0.5, 0.0, 1.0]] * 3)
    q = np.cumsum(qd * 0.05, axis=0)
    assert first_sensor_fault(*readings(q, qd), LIMITS) is None
    high = q.copy()
    high[2, 0] = 0.75  # 0.15 beyond the boom's 0.6 (margin 0.1)
    fault = first_sensor_fault(*readings(high, qd), LIMITS)
    assert fault is not None and (fault.reading, fault.joint, fault.kind) == (2, 0, "position")
    assert fault.describe() == "boom reads 0.750 rad, beyond its joint limit 0.600 rad"
    fast = qd.copy()
    fast[1, 2] = -3.5
    fault = first_sensor_fault(*readings(q, fast), LIMITS, tolerance=1.0)
    assert fault is not None and (fault.reading, fault.joint, fault.kind, fault.value) == (1, 2, "speed", -3.5)
    jumped = q.copy()
    jumped[2, 1] += 0.2  # 0.2 rad more than 0.5 rad/s allows in 50 ms
    fault = first_sensor_fault(*readings(jumped, qd), LIMITS)
    assert fault is not None and (fault.reading, fault.joint, fault.kind) == (2, 1, "motion")
    assert fault.value == pytest.approx(0.225) and fault.limit == pytest.approx(0.025)
    assert first_sensor_fault(*readings(jumped, qd), LIMITS, tolerance=0.21) is None


def test_a_velocity_that_jumps_within_a_period_and_the_swing_across_pi_are_no_fault():
    q = np.array([[0.0, 0, 0, math.pi - 0.02], [-0.05, 0, 0, -math.pi + 0.03]])  # boom from rest to −1 rad/s
    qd = np.array([[0.0, 0, 0, 1.0], [-1.0, 0, 0, 1.0]])
    assert first_sensor_fault(*readings(q, qd), LIMITS) is None
    swing_limited = GuardLimits(q_min=(-0.5, -1, -0.5, -1.0), q_max=(0.6, 0.5, 2.3, 1.0))
    fault = first_sensor_fault(*readings(q, qd), swing_limited)
    assert fault is not None and (fault.joint, fault.kind) == (3, "position")


def test_a_repeated_or_late_sample_is_not_judged_on_its_motion():
    obs, _ = readings([[0.0] * 4, [0.3, 0, 0, 0]], [[0.0] * 4, [0.0] * 4])
    assert first_sensor_fault(obs, np.array([1.0, 1.0]), LIMITS) is None
    assert first_sensor_fault(obs, np.array([1.0, 1.05]), LIMITS) is not None


@pytest.mark.skipif(not REAL_LOGS.is_dir(), reason="the real XE75 logs are not here (../shared/data/xe75)")
def test_no_reading_of_the_real_xe75_logs_is_a_sensor_fault():
    limits = GuardLimits.load(limits_preset_path("xe75"))
    files = sorted(REAL_LOGS.glob("*/*.npz"))
    assert len(files) == 640
    for path in files:
        with np.load(path) as log:
            obs, stamps = np.concatenate([log["q"], log["qd"]], axis=1), log["t"]
        assert first_sensor_fault(obs, stamps, limits) is None, path


class WildBoom(SimulatedMachine):
    """A user's adapter (``--machine test_sensor:WildBoom``): the toy system at rest, whose boom reading jumps by 1 rad
    per read from tick 21 on."""

    def __init__(self, clock=None):
        super().__init__(BatchedSystem(make()), np.zeros(4), *(() if clock is None else (clock,)))
        self.reads, self.sent = 0, []

    def read(self):
        reading = super().read()
        k, self.reads = self.reads, self.reads + 1  # read 0 is the start's, read k that of tick k
        obs = reading.obs.copy()
        obs[0] += max(k - FAULT_TICK + 1, 0)
        return Reading(obs, reading.stamp)

    def send(self, q_ref):
        self.sent.append(np.array(q_ref))
        return super().send(q_ref)


def test_a_wild_sensor_stops_the_loop_at_its_first_tick_and_holds_the_last_reference(tmp_path):
    ref = sine_refs([60], seed=2)[0]
    clock = FakeClock()
    machine = WildBoom(clock)
    machine.q0 = ref.q[0]
    with TickLog(tmp_path / "log.jsonl") as log:
        loop = Loop(Runtime(LinearPolicy(horizon=3), limits=None), machine, DEFAULT_LIMITS, clock=clock, log=log)
        result = loop.run(ref.q, "wild")
    assert result.reason == "sensor_fault" and result.ticks == FAULT_TICK + 1
    pattern = rf"tick {FAULT_TICK}: boom moved (0\.9|1\.0)\d\d rad in one reading, where its velocities allow -?0\.\d{{3}} rad"
    assert re.fullmatch(pattern, result.error), result.error
    np.testing.assert_array_equal(machine.sent[-1], machine.sent[-2])  # held, not steered by the faulty reading
    lines = [json.loads(line) for line in (tmp_path / "log.jsonl").read_text().splitlines()]
    assert "sensor_fault" in lines[FAULT_TICK]["events"] and all(v is None for v in lines[FAULT_TICK]["obs"])
    assert lines[-1]["reason"] == "sensor_fault"


def test_a_first_reading_beyond_the_limits_sends_nothing():
    machine = WildBoom()
    machine.q0 = np.array([0.75, 0.0, 0.0, 0.0])  # 0.15 beyond the boom's limit, near a reference inside it
    with pytest.raises(EfficientTrackError, match="sensor fault in the first reading: boom reads 0.750 rad"):
        Loop(Runtime(None, limits=None), machine, LIMITS, clock=FakeClock()).run(np.tile([0.55, 0, 0, 0], (10, 1)), "far")
    assert machine.sent == []


@pytest.fixture
def at_rest(tmp_path):
    """A 40-step reference at rest where WildBoom starts, and an empty limits file (the default limits)."""
    save_references([Reference("rest", np.zeros((40, 4)))], tmp_path / "refs")
    (tmp_path / "lim.json").write_text("{}")
    return ("--refs", tmp_path / "refs", "--machine", "test_sensor:WildBoom", "--limits", tmp_path / "lim.json", "--arm")


def test_deploy_arm_exits_1_naming_the_joint_and_tick_of_a_wild_sensor(at_rest, tmp_path):
    result = invoke("deploy", *at_rest, "--out", tmp_path / "o")
    assert result.exit_code == 1 and f"rest: sensor_fault, {FAULT_TICK + 1} ticks" in result.output
    assert f"tick {FAULT_TICK}: boom moved" in result.output
    end = json.loads((tmp_path / "o" / "rest.jsonl").read_text().splitlines()[-1])
    assert end["reason"] == "sensor_fault" and end["ticks"] <= FAULT_TICK + 5


def test_collect_arm_stops_at_a_wild_sensor_and_names_joint_and_tick(at_rest, tmp_path):
    result = invoke("collect", *at_rest, "--out", tmp_path / "c", "--passes", "1")
    assert result.exit_code != 0
    assert f"sensor_fault: tick {FAULT_TICK}: boom moved" in str(result.exception)
    end = json.loads((tmp_path / "c" / "logs" / "pass_000" / "rest.jsonl").read_text().splitlines()[-1])
    assert end["reason"] == "sensor_fault" and end["ticks"] <= FAULT_TICK + 5


def unreachable_machine():
    """A user's adapter factory (``--machine test_sensor:unreachable_machine``) whose connection fails."""
    raise ConnectionRefusedError("CAN interface can0 is down")


def test_a_machine_factory_that_raises_is_one_clear_error(at_rest, tmp_path):
    args = [a if a != "test_sensor:WildBoom" else "test_sensor:unreachable_machine" for a in at_rest]
    result = invoke("deploy", *args, "--out", tmp_path / "o")
    assert isinstance(result.exception, EfficientTrackError)
    assert str(result.exception) == (
        "machine 'test_sensor:unreachable_machine': building the adapter failed (ConnectionRefusedError: CAN interface "
        "can0 is down); nothing was sent"
    )


PAPER_REF_28 = REAL_LOGS.parent / "references" / "train" / "ref_28.npy"


@pytest.mark.skipif(not PAPER_REF_28.is_file(), reason="the shared references are not here (../shared/data/references)")
def test_the_paper_simulators_fast_bucket_is_no_sensor_fault_in_the_loop():
    """ref_28 drives the paper simulator's bucket at 6.6 rad/s under PD, beyond the default 2π rad/s."""
    from efficienttrack.data.references import load_references
    from efficienttrack.systems.spec import SystemSpec

    [ref] = load_references(PAPER_REF_28)
    system = SystemSpec(system="paper").open()
    clock = FakeClock()
    result = Loop(Runtime(None, limits=None), SimulatedMachine(system, ref.q[0], clock), system.limits, clock=clock).run(
        ref.q, ref.name
    )
    assert result.reason == "done", result.error

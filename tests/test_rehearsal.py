"""Rehearsing a real machine: the built-in simulated machine for ``--machine``, and the approach between episodes."""

import json
from pathlib import Path

import numpy as np
import pytest

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.data.records import load_records
from efficienttrack.data.references import Reference, load_references, save_references
from efficienttrack.deploy.deployment import APPROACH_SPEED, approach_path, run_episode
from efficienttrack.deploy.loop import NotAtStart
from efficienttrack.deploy.machine import SimulatedClock, simulated
from test_loop import invoke

SIMULATED = "efficienttrack.deploy.machine:simulated"


@pytest.fixture
def refs(tmp_path):
    """Three 3 s pieces of a generated cycle, one after the other: every step is a tick of the loop, and so is every step
    of the approaches, which take the longer the farther apart the starts are (0.1 rad/s)."""
    assert invoke("refs", "generate", "--n", "1", "--seed", "3", "--out", tmp_path / "gen").exit_code == 0
    [cycle] = load_references(tmp_path / "gen")
    save_references([Reference(f"ref_0{k + 1}", cycle.q[60 * k : 60 * (k + 1)]) for k in range(3)], tmp_path / "refs")
    (tmp_path / "lim.json").write_text("{}")
    return tmp_path / "refs"


def machine_args(tmp_path, name, *options):
    opts = [arg for option in (f"name={name}", *options) for arg in ("--machine-opt", option)]
    return ("--machine", SIMULATED, *opts, "--limits", tmp_path / "lim.json", "--arm", "--fast")


def test_the_simulated_machine_stays_where_its_last_episode_left_it():
    clock = SimulatedClock()
    first = simulated(start="0.1,0.2,0.3,0.4", name="stays", clock=clock)
    with first:
        assert np.allclose(first.read().obs[:4], [0.1, 0.2, 0.3, 0.4])
        for _ in range(40):
            first.send(np.array([0.3, 0.2, 0.3, 0.4]))
        moved = first.read().obs[:4]
    assert moved[0] > 0.2
    with simulated(start="0.1,0.2,0.3,0.4", name="stays", clock=clock) as again:  # the same machine, not reset
        assert np.allclose(again.read().obs[:4], moved)
    with simulated(name="another", clock=clock) as other:
        assert not np.allclose(other.read().obs[:4], moved)
    for bad, match in (({"fault": "smoke"}, "fault 'smoke' is none of"), ({"start": "1,2"}, "expected four finite numbers"),
                       ({"system": "learned"}, "no built-in physical system"),
                       ({"fault_episode": "two"}, "fault_episode must be a whole number")):  # fmt: skip
        with pytest.raises(EfficientTrackError, match=match):
            simulated(name="bad", **bad)


def test_an_approach_goes_the_short_way_round_at_its_speed_then_holds():
    path = approach_path(np.array([0.0, 0.1, 0.2, 3.0]), np.array([0.1, 0.1, 0.2, -3.0]))
    steps = np.abs(np.diff(path, axis=0))
    steps[:, 3] = np.minimum(steps[:, 3], 2 * np.pi - steps[:, 3])
    assert steps.max() <= APPROACH_SPEED * 0.05 + 1e-9  # 2π − 6 rad of swing through ±π, not 6 rad
    assert np.allclose(path[-40:], [0.1, 0.1, 0.2, -3.0])
    bucket = approach_path(np.array([0.0, 0.0, -1.0, 0.0]), np.array([0.0, 0.0, 3.0, 0.0]))[:, 2]
    assert np.all(np.diff(bucket) >= 0) and bucket[-1] == pytest.approx(3.0)  # only the swing wraps: 4 rad up, not 2.3 down


@pytest.mark.slow
def test_collect_on_the_simulated_machine_approaches_every_start_and_runs_every_episode(tmp_path, refs):
    result = invoke("collect", "--refs", refs, "--out", tmp_path / "c", *machine_args(tmp_path, "collect"), "--passes", "2")
    assert result.exit_code == 0, result.output
    assert "collected 6 episodes" in result.output
    assert "the machine stands" in result.output and "approaching it through the loop (try 1 of 3" in result.output
    for k in (0, 1):
        logs = tmp_path / "c" / "logs" / f"pass_{k:03d}"
        assert sorted(p.name for p in logs.glob("*.jsonl")) == [f"ref_{i:02d}.jsonl" for i in range(1, 4)]
        approaches = sorted(p.name for p in (logs / "approach").glob("*.jsonl"))
        assert approaches, "the machine never had to move to a start"
        for path in (logs / "approach").glob("*.jsonl"):
            assert json.loads(path.read_text().splitlines()[-1])["reason"] == "done"
    records = load_records(tmp_path / "c", recursive=True)
    assert len(records) == 6 and all(not r.meta["name"].endswith("(approach)") for r in records)


def test_without_an_approach_an_episode_away_from_its_start_stops_and_leaves_no_empty_log(tmp_path, refs):
    args = ("collect", "--refs", refs, "--out", tmp_path / "c", *machine_args(tmp_path, "stop"), "--passes", "1")
    result = invoke(*args, "--between-episodes", "stop")
    assert "from the reference's first position" in str(result.exception) and "--between-episodes approach" in str(
        result.exception
    )
    logs = tmp_path / "c" / "logs" / "pass_000"
    assert sorted(p.name for p in logs.iterdir()) == []  # the first episode starts away from where the machine stands
    assert "expected one of approach, prompt, stop" in str(invoke(*args, "--between-episodes", "pray").exception)


@pytest.mark.parametrize(
    ("fault", "reason"),
    [("read_error", "read_error"), ("send_error", "send_error"), ("stale", "stale_sensor"), ("nan", "stale_sensor"),
     ("drop", "stale_sensor"), ("late", "overruns")],
)  # fmt: skip
def test_the_simulated_machines_faults_stop_a_deployment(tmp_path, refs, fault, reason):
    one = tmp_path / "one"
    one.mkdir()
    (one / "ref_01.npy").write_bytes((refs / "ref_01.npy").read_bytes())
    # opened: a refused start (the machine stands 0.2 rad away, a short approach), the approach, the episode
    start = ",".join(map(str, np.load(one / "ref_01.npy")[0] + [0.2, 0, 0, 0]))
    options = (f"start={start}", f"fault={fault}", "fault_at=30", "fault_episode=3")
    result = invoke("deploy", "--refs", one, "--out", tmp_path / "d", *machine_args(tmp_path, f"fault-{fault}", *options))
    assert result.exit_code == 1, result.output
    assert f"stopped: ref_01: {reason}" in result.output


def test_adapter_options_are_read_as_set_reads_values_and_keep_nan_and_inf_as_words():
    from efficienttrack.cli.common import parse_options
    from efficienttrack.core.errors import EfficientTrackError

    parsed = parse_options(["fault=nan", "level=inf", "fault_at=30", "scale=1e-1", "armed=true", "port=can0"], "--machine-opt")
    assert parsed == {"fault": "nan", "level": "inf", "fault_at": 30, "scale": 0.1, "armed": True, "port": "can0"}
    with pytest.raises(EfficientTrackError, match=r"--machine-opt 'gains=\[1, 2': the value is not valid YAML"):
        parse_options(["gains=[1, 2"], "--machine-opt")


def test_homed_references_start_and_end_at_home_led_in_and_out_slowly(tmp_path):
    from efficienttrack.data.cycles import HOME_SPEED, generate_references, homed
    from efficienttrack.data.references import load_references

    home = np.array([0.1, -0.5, 1.0, 3.1])
    cycles = generate_references(2, seed=4)
    for ref, cycle in zip(homed(cycles, home), cycles, strict=True):
        assert np.allclose(ref.q[0], home) and np.allclose(ref.q[-1], home)
        lead_in = len(ref.q) - len(cycle.q)
        inside = next(i for i in range(lead_in) if np.allclose(ref.q[i : i + len(cycle.q)], cycle.q))
        step = np.abs(np.diff(ref.q[: inside + 1], axis=0))
        step[:, 3] = np.minimum(step[:, 3], 2 * np.pi - step[:, 3])  # the swing goes the short way through ±π
        assert step.max() <= HOME_SPEED * 0.05 + 1e-9
    assert invoke("refs", "generate", "--n", "3", "--home", "0.1,-0.5,1.0,0.0", "--out", tmp_path / "refs").exit_code == 0
    assert all(np.allclose(r.q[[0, -1]], [0.1, -0.5, 1.0, 0.0]) for r in load_references(tmp_path / "refs"))
    assert "--home '1,2': expected four finite numbers" in str(
        invoke("refs", "generate", "--home", "1,2", "--out", tmp_path / "x").exception
    )


def test_the_prompt_asks_the_operator_with_the_start_and_retries_or_stops():
    ref = Reference("ref_01", np.tile([0.1, 0.2, 0.3, 3.1], (40, 1)))
    away = NotAtStart("too far", np.array([0.0, 0.2, 0.3, -3.1]))
    attempts, asked = [], []

    def run():
        attempts.append(1)
        if len(attempts) == 1:
            raise away
        return "ran"

    def operator(answer):
        def ask(question):
            asked.append(question)
            if answer is EOFError:
                raise EOFError
            return answer

        return ask

    args = (None, None, None, None, Path("logs"))
    assert run_episode(ref, run, "prompt", *args, ask=operator("")) == "ran" and len(attempts) == 2
    assert asked[0].startswith("ref_01: bring the machine to the start (boom 5.7°, arm 11.5°, bucket 17.2°, swing 177.6°")
    assert "to go: boom +5.7°, arm +0.0°, bucket +0.0°, swing -4.8°" in asked[0]  # the swing the short way round
    for answer in ("q", EOFError):  # the operator stops, or there is none
        attempts.clear()
        with pytest.raises(NotAtStart):
            run_episode(ref, run, "prompt", *args, ask=operator(answer))
        assert len(attempts) == 1


def test_the_prompt_needs_a_terminal(tmp_path, refs):
    args = ("collect", "--refs", refs, "--out", tmp_path / "c", *machine_args(tmp_path, "prompt"), "--passes", "1")
    result = invoke(*args, "--between-episodes", "prompt")
    assert "--between-episodes prompt: asks an operator at a terminal" in str(result.exception)
    assert not (tmp_path / "c").exists()

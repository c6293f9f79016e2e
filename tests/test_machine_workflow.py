"""A machine from its first collection to a deployed policy and a second round, all through the fixed-rate loop.

Collection (Algorithm 1) runs on a :class:`~efficienttrack.deploy.loop.Machine` adapter through the loop that deploys,
on a simulated clock here; the fault-injecting adapters of ``test_loop`` stop and interrupt it.
"""

import json

import numpy as np
import pytest

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.data.records import load_records
from efficienttrack.data.references import Reference, load_references, save_references
from efficienttrack.deploy.machine import SimulatedMachine
from efficienttrack.systems.limits import DEFAULT_LIMITS
from efficienttrack.systems.protocol import BatchedSystem
from efficienttrack.workflow.collect import CollectConfig, LoopMachine, collect, episode_noise
from test_loop import FakeClock, FaultyMachine, invoke
from toy_system import make, sine_refs

NOISY = CollectConfig(sigma_max=0.05, noise_ratio=(1.0, 0.0), passes=1, seed=3)


def loop_machine(clock=None, **faults_by_reference):
    """The toy system as a LoopMachine; ``faults_by_reference``: reference name → FaultyMachine faults of its episode."""
    clock = clock or FakeClock()
    opened = []

    def make_machine(ref):
        machine = FaultyMachine(ref.q[0], clock, **faults_by_reference.get(ref.name, {}))
        opened.append(ref.name)
        return machine

    return LoopMachine(make_machine, DEFAULT_LIMITS, clock, "toy"), opened


def test_collecting_through_the_loop_sends_algorithm_1s_noise_within_the_loops_rules(tmp_path):
    refs = sine_refs([50, 70], seed=4)
    machine, _ = loop_machine()
    result = collect(machine, refs, NOISY, tmp_path / "c", progress=False)
    assert [r.meta["name"] for r in result.records] == ["ref_00", "ref_01"]
    assert result.interaction_steps == sum(ref.steps for ref in refs)
    rate = np.asarray(DEFAULT_LIMITS.max_adjust_rate)
    for i, (ref, record) in enumerate(zip(refs, result.records, strict=True)):
        sigma, noise = episode_noise(NOISY, 0, i, ref.steps)
        a = record.q_ref - record.q_des
        assert record.meta["sigma"] == sigma and record.meta["noisy"] and record.meta["source"] == "collect"
        assert not a[0].any() and not a[-1].any()  # a = 0 at the start and at the end
        assert np.all(np.abs(np.diff(a, axis=0)) <= rate + 1e-12)  # the loop's rate limit
        free = [k for k in range(1, ref.steps - 1) if k not in record.meta["loop_events"].get("ramped", [])]
        np.testing.assert_allclose(a[free], noise[free], atol=1e-12)  # elsewhere the episode's own seeded noise
        assert len(free) > ref.steps // 2
    logs = sorted(p.name for p in (tmp_path / "c" / "logs" / "pass_000").iterdir())
    assert logs == ["ref_00.jsonl", "ref_01.jsonl"]
    manifest = json.loads((tmp_path / "c" / "collect.json").read_text())
    assert manifest["loop"]["machine"] == "toy"
    again = collect(loop_machine()[0], refs, NOISY, tmp_path / "c", progress=False)
    assert again.resumed_passes == 1 and again.interaction_steps == result.interaction_steps
    with pytest.raises(EfficientTrackError, match="other settings"):  # a batched collection is another collection
        collect(BatchedSystem(make()), refs, NOISY, tmp_path / "c", progress=False)


def test_a_watchdog_stop_keeps_the_episodes_before_it_and_a_rerun_resumes_there(tmp_path):
    refs = sine_refs([40, 40, 40], seed=5)
    dying, opened = loop_machine(ref_01={"drop": range(10, 100)})
    with pytest.raises(EfficientTrackError, match=r"reference ref_01: the loop stopped it .*stale_sensor.*rerun"):
        collect(dying, refs, NOISY, tmp_path / "c", progress=False)
    assert opened == ["ref_00", "ref_01"]
    assert [r.meta["name"] for r in load_records(tmp_path / "c" / ".pass_000.partial")] == ["ref_00"]
    healthy, opened = loop_machine()
    result = collect(healthy, refs, NOISY, tmp_path / "c", progress=False)
    assert opened == ["ref_01", "ref_02"]  # the recorded episode is not run again
    assert [r.meta["name"] for r in result.records] == ["ref_00", "ref_01", "ref_02"]
    logs = tmp_path / "c" / "logs" / "pass_000"
    assert (logs / "ref_01.stopped-1.jsonl").exists() and (logs / "ref_01.jsonl").exists()  # nothing recorded is lost


def test_ctrl_c_during_an_episode_reaches_the_command_after_the_machine_is_closed(tmp_path):
    refs = sine_refs([40, 40], seed=6)
    machine, opened = loop_machine(ref_01={"interrupt": 7})
    with pytest.raises(KeyboardInterrupt):
        collect(machine, refs, NOISY, tmp_path / "c", progress=False)
    assert [r.meta["name"] for r in load_records(tmp_path / "c" / ".pass_000.partial")] == ["ref_00"]
    end = json.loads((tmp_path / "c" / "logs" / "pass_000" / "ref_01.jsonl").read_text().splitlines()[-1])
    assert end["reason"] == "interrupted"


def test_a_dropped_sample_splits_the_episode_and_resuming_reads_every_part(tmp_path):
    refs = sine_refs([60], seed=7)
    machine, _ = loop_machine(ref_00={"drop": [20]})
    result = collect(machine, refs, NOISY, tmp_path / "c", progress=False)
    assert [r.meta["name"] for r in result.records] == ["ref_00", "ref_00-2"]
    assert [r.meta["reference"] for r in result.records] == ["ref_00", "ref_00"]
    again = collect(loop_machine()[0], refs, NOISY, tmp_path / "c", progress=False)
    assert [r.meta["name"] for r in again.records] == ["ref_00", "ref_00-2"]


class RestingXe75(SimulatedMachine):
    """A user's adapter written once (``--machine test_machine_workflow:RestingXe75``): the xe75 simulator, started
    where every test reference starts, read and sent in real time."""

    START = np.array([0.1, -0.5, 1.0, 0.0])

    def __init__(self):
        from efficienttrack.systems.spec import SystemSpec

        super().__init__(SystemSpec().open(), self.START)


def there_and_back(name, steps, amplitude, seed):
    """A reference from RestingXe75.START out and back, (steps, 4) rad."""
    rng = np.random.default_rng(seed)
    shape = np.sin(np.linspace(0, np.pi, steps)) ** 2
    return Reference(name, RestingXe75.START + shape[:, None] * amplitude * rng.uniform(-1, 1, 4))


@pytest.mark.slow
def test_collect_on_a_users_machine_adapter_runs_in_real_time_and_needs_arm_and_limits(tmp_path):
    save_references([there_and_back("short", 12, 0.1, 0)], tmp_path / "refs")
    (tmp_path / "lim.json").write_text("{}")
    args = ("collect", "--refs", tmp_path / "refs", "--out", tmp_path / "c", "--machine", "test_machine_workflow:RestingXe75")
    assert "add --arm" in str(invoke(*args, "--limits", tmp_path / "lim.json").exception)
    assert "--machine needs --limits" in str(invoke(*args, "--arm").exception)
    result = invoke(*args, "--limits", tmp_path / "lim.json", "--arm", "--passes", "1", "--sigma-max", "0.02")
    assert result.exit_code == 0, result.output
    assert "collected 1 episodes, 11 interaction steps" in result.output
    [record] = load_records(tmp_path / "c" / "pass_000")
    assert np.all(np.diff(record.t) == pytest.approx(0.05))


@pytest.mark.slow
def test_from_first_collection_to_a_second_round_on_the_simulated_machine(tmp_path):
    """docs/your-machine.md's rehearsal: collect → train-model → train-policy → deploy --shadow → deploy → round, on one
    simulated machine through --machine, which stays where each episode left it and approaches every start."""
    assert invoke("refs", "generate", "--n", "1", "--seed", "5", "--out", tmp_path / "gen").exit_code == 0
    # two 3 s pieces of the cycle, one after the other: every step is a tick of the loop, and so is every step of the
    # approaches, which take the longer the farther apart the starts are (0.1 rad/s)
    [cycle] = load_references(tmp_path / "gen")
    save_references([Reference(f"ref_0{k + 1}", cycle.q[60 * k : 60 * (k + 1)]) for k in (0, 1)], tmp_path / "refs")
    (tmp_path / "limits.yaml").write_text("{}")
    machine = ("--machine", "efficienttrack.deploy.machine:simulated", "--machine-opt", f"name={tmp_path}",
               "--limits", tmp_path / "limits.yaml", "--arm", "--fast")  # fmt: skip
    steps = ("--preset", "tiny", "--set", "model.steps=30", "--set", "policy.steps=20")
    for args in (
        ("collect", *machine, "--refs", tmp_path / "refs", "--out", tmp_path / "round1", "--passes", "2"),
        ("train-model", "--data", tmp_path / "round1", "-r", "--out", tmp_path / "model.pt", *steps),
        ("train-policy", "--model", tmp_path / "model.pt", "--data", tmp_path / "round1", "-r",
         "--out", tmp_path / "policy.pt", *steps),
        ("deploy", *machine, "--refs", tmp_path / "refs", "--policy", tmp_path / "policy.pt", "--out", tmp_path / "shadow",
         "--shadow"),
        ("deploy", *machine, "--refs", tmp_path / "refs", "--policy", tmp_path / "policy.pt", "--out", tmp_path / "armed"),
        ("round", "--model", tmp_path / "model.pt", "--policy", tmp_path / "policy.pt", "--data", tmp_path / "armed/records",
         "--old-data", tmp_path / "round1", "-r", "--out", tmp_path / "round2", *steps),
    ):  # fmt: skip
        result = invoke(*args)
        assert result.exit_code == 0, f"{args[0]}: {result.output}"
        if args[0] == "deploy":
            assert "tracking with" in result.output and "2 run(s) done" in result.output
    assert len(load_records(tmp_path / "round1", recursive=True)) == 4
    assert list((tmp_path / "round1" / "logs" / "pass_000" / "approach").glob("*.jsonl")), "no start was approached"
    shadow = json.loads((tmp_path / "shadow" / "deploy.json").read_text())["tracking"]
    armed = json.loads((tmp_path / "armed" / "deploy.json").read_text())["tracking"]
    assert shadow["episodes"] == armed["episodes"] == 2 and shadow["mae_deg"] != armed["mae_deg"]
    assert (tmp_path / "round2" / "policy.pt").exists() and (tmp_path / "round2" / "round.json").exists()

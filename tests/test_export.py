"""`efficienttrack export` and the torch-free ONNX runtime: parity with torch, the contract, a run without torch."""

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from efficienttrack.cli import app
from efficienttrack.core.errors import EXTRAS, EfficientTrackError
from efficienttrack.core.joints import DT, JOINT_NAMES
from efficienttrack.data.dataset import Sequences
from efficienttrack.data.records import save_records
from efficienttrack.deploy import export as export_module
from efficienttrack.deploy.episodes import Guard
from efficienttrack.deploy.export import export_policy
from efficienttrack.deploy.onnx_runtime import CONTRACT_FILE, ONNX_FILE, OnnxRuntime, load_onnx_policy
from efficienttrack.deploy.runtime import Runtime, track
from efficienttrack.learn.policy import AdjustmentPolicy, save_policy
from efficienttrack.learn.settings import PolicyConfig
from efficienttrack.systems.limits import GuardLimits
from efficienttrack.systems.protocol import BatchedSystem
from toy_system import make, sine_refs

SRC = Path(__file__).resolve().parents[1] / "src"
LIMITS = GuardLimits(max_adjust_rate=(0.03,) * 4)
"""Tight enough that the rate limit acts on the random policy's adjustments (the guard's path is compared too)."""


def toy_policy(records, horizon=3, seed=0):
    """A tiny policy scaled on recorded windows, with a random (seeded) last layer so that it adjusts."""
    torch.manual_seed(seed)
    policy = AdjustmentPolicy(PolicyConfig(hidden=16, layers=2, horizon=horizon))
    seqs = Sequences(records, history=horizon, future=horizon)
    w = seqs.window(seqs.starts(0), horizon=0, desired=horizon)
    policy.fit_scaling(w.obs_hist, w.qref_hist, w.qdes_future)
    torch.nn.init.normal_(policy.pi_phi.body[-1].weight, std=0.5)
    return policy.eval()


@pytest.fixture(scope="module")
def logged():
    """PD logs of the toy system, a policy scaled on them, and the policy's own guarded log (torch runtime)."""
    refs = sine_refs([60, 45, 70], seed=2)
    pd_records = track(BatchedSystem(make()), None, refs, progress=False)
    policy = toy_policy(pd_records)
    records = track(BatchedSystem(make()), policy, refs, progress=False, limits=LIMITS)
    return policy, records


@pytest.fixture(scope="module")
def exported(logged, tmp_path_factory):
    return export_policy(logged[0], tmp_path_factory.mktemp("export") / "out", {"checkpoint": "policy.pt"})


def test_onnx_equals_torch_on_recorded_windows(logged, exported):
    policy, records = logged
    onnx_policy = load_onnx_policy(exported)
    seqs = Sequences(records, history=3, future=3)
    w = seqs.window(seqs.starts(0), horizon=0, desired=3)
    with torch.no_grad():
        expected = policy(w.obs_hist, w.qref_hist, w.qdes_future).numpy()
    got = onnx_policy(w.obs_hist.numpy(), w.qref_hist.numpy(), w.qdes_future.numpy())
    assert got.shape == expected.shape == (seqs.steps, 4)  # the batch axis is dynamic
    assert np.abs(expected).max() > 0.05  # the policy really adjusts
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-5)
    one = onnx_policy(w.obs_hist[:1].numpy(), w.qref_hist[:1].numpy(), w.qdes_future[:1].numpy())
    np.testing.assert_allclose(one, expected[:1], rtol=0, atol=1e-5)


def test_contract_states_the_interface(logged, exported):
    contract = json.loads((exported / CONTRACT_FILE).read_text())
    assert contract["joint_order"] == list(JOINT_NAMES)
    assert (contract["dt"], contract["history_length"], contract["future_length"]) == (DT, 3, 3)
    assert [(i["name"], i["shape"]) for i in contract["inputs"]] == [
        ("obs_hist", ["batch", 3, 8]),
        ("qref_hist", ["batch", 3, 4]),
        ("qdes_future", ["batch", 3, 4]),
    ]
    assert contract["output"]["shape"] == ["batch", 4]
    assert contract["max_adjust"] == list(logged[0].cfg.max_adjust)
    assert contract["policy_config"]["hidden"] == 16
    assert contract["source"] == {"checkpoint": "policy.pt"}
    assert contract["package_version"] and contract["units"]["angle"] == "rad"


def test_onnx_runtime_runs_the_same_guarded_step(logged, exported):
    """In-process: the ONNX runtime has the torch runtime's interface and lengths, and the guard's fallbacks."""
    policy, _ = logged
    onnx_rt, torch_rt = OnnxRuntime(load_onnx_policy(exported), limits=LIMITS), Runtime(policy, limits=LIMITS)
    assert (onnx_rt.history_length, onnx_rt.future_length) == (torch_rt.history_length, torch_rt.future_length)
    np.testing.assert_array_equal(onnx_rt.max_adjust, torch_rt.max_adjust)
    obs = np.zeros((2, 8))
    with onnx_rt, torch_rt:
        for rt in (onnx_rt, torch_rt):
            rt.start(obs)
        q_des = np.full((2, 3, 4), 0.1)
        bad = obs.copy()
        bad[1, 2] = np.nan
        a, b = onnx_rt.step(bad, q_des), torch_rt.step(bad, q_des)
    np.testing.assert_allclose(a.q_ref, b.q_ref, atol=1e-5)
    np.testing.assert_array_equal(a.guard, b.guard)
    assert a.fallback.tolist() == [False, True]
    assert not onnx_rt.running


def test_both_runtimes_fall_back_after_dropped_samples_and_start_afresh(logged, exported):
    onnx_rt, torch_rt = OnnxRuntime(load_onnx_policy(exported), limits=LIMITS), Runtime(logged[0], limits=LIMITS)
    q_des = np.full((1, 3, 4), 0.1)
    sent = {}
    for name, rt in (("onnx", onnx_rt), ("torch", torch_rt)):
        rt.start(np.zeros((1, 8)), t=0.0)
        rt.step(np.zeros((1, 8)), q_des, t=DT)
        moved = np.zeros((1, 8))
        moved[0, 0] = 0.2
        sent[name] = [rt.step(moved, q_des, t=7 * DT), rt.step(moved, q_des, t=8 * DT)]  # 5 periods without a call
    for a, b in zip(sent["onnx"], sent["torch"], strict=True):
        np.testing.assert_allclose(a.q_ref, b.q_ref, atol=1e-5)
        np.testing.assert_array_equal(a.guard, b.guard)
    assert sent["onnx"][0].guard[0] == Guard.OBS_STALE and not sent["onnx"][1].fallback[0]
    np.testing.assert_array_equal(onnx_rt._history.obs, torch_rt._history.obs)


BLOCK_TORCH = """
import importlib.abc, sys

class NoTorch(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name == "torch" or name.startswith("torch."):
            raise ModuleNotFoundError("No module named 'torch' (blocked by the test)")

sys.meta_path.insert(0, NoTorch())
"""

REPLAY = """
import numpy as np
from efficienttrack.deploy.onnx_runtime import OnnxRuntime, load_onnx_policy
from efficienttrack.data.records import load_records
from efficienttrack.systems.limits import GuardLimits

export, logs, limits, out = sys.argv[1:5]
runtime = OnnxRuntime(load_onnx_policy(export), limits=GuardLimits.load(limits))
sent, guard = [], []
for record in load_records(logs):
    T, F = len(record), runtime.future_length
    future = record.q_des[np.minimum(np.arange(T)[:, None] + np.arange(F), T - 1)]  # (T, F, 4), last one repeated
    with runtime:
        runtime.start(record.obs[:1])
        for t in range(T):
            step = runtime.step(record.obs[t : t + 1], future[t : t + 1])
            sent.append(step.q_ref[0])
            guard.append(step.guard[0])
np.savez(out, q_ref=np.array(sent), guard=np.array(guard))
assert "torch" not in sys.modules, "the ONNX runtime imported torch"
"""


def test_onnx_runtime_without_torch_sends_what_the_torch_runtime_sent(logged, exported, tmp_path):
    _, records = logged
    logs = tmp_path / "logs"
    save_records(records, logs)
    (tmp_path / "limits.json").write_text(json.dumps(LIMITS.to_dict()))
    script = tmp_path / "replay.py"
    script.write_text(BLOCK_TORCH + REPLAY)
    env = {**os.environ, "PYTHONPATH": str(SRC)}
    args = [sys.executable, str(script), str(exported), str(logs), str(tmp_path / "limits.json"), str(tmp_path / "out.npz")]
    done = subprocess.run(args, capture_output=True, text=True, env=env, timeout=120)
    assert done.returncode == 0, done.stderr
    replay = np.load(tmp_path / "out.npz")
    # save_records writes the records in name order; they are named by track in the order of the references
    np.testing.assert_allclose(replay["q_ref"], np.concatenate([r.q_ref for r in records]), rtol=0, atol=1e-5)
    assert sum(len(r.meta["guard"].get("rate_limited", [])) for r in records) > 0  # the guard acted on the log
    logged_guard = np.zeros(len(replay["guard"]), dtype=np.uint16)
    offset = 0
    for record in records:
        for reason, steps in record.meta["guard"].items():
            logged_guard[offset + np.array(steps)] |= Guard[reason.upper()].value
        offset += len(record)
    np.testing.assert_array_equal(replay["guard"], logged_guard)


def test_the_blocker_really_blocks_torch(tmp_path):
    script = tmp_path / "check.py"
    script.write_text(BLOCK_TORCH + "import torch\n")
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=60)
    assert done.returncode != 0 and "blocked by the test" in done.stderr


def test_damaged_or_mismatched_exports_are_refused(exported, tmp_path):
    folder = tmp_path / "copy"
    folder.mkdir()
    graph, contract = (exported / ONNX_FILE).read_bytes(), json.loads((exported / CONTRACT_FILE).read_text())

    def write(graph_bytes, **fields):
        (folder / ONNX_FILE).write_bytes(graph_bytes)
        (folder / CONTRACT_FILE).write_text(json.dumps({**contract, **fields}))

    write(graph[:-10] + b"0123456789")
    with pytest.raises(EfficientTrackError, match="does not match the SHA-256"):
        load_onnx_policy(folder)
    write(graph, history_length=5)
    with pytest.raises(EfficientTrackError, match="inputs .* are not those of policy.json"):
        load_onnx_policy(folder)
    write(graph, max_adjust=[0.1, 0.1, float("inf"), 0.1])
    with pytest.raises(EfficientTrackError, match="field 'max_adjust' must be 4 positive numbers"):
        load_onnx_policy(folder)
    write(graph, format_version=99)
    with pytest.raises(EfficientTrackError, match="field 'format_version' is 99"):
        load_onnx_policy(folder)
    write(b"not a graph", onnx_sha256=hashlib.sha256(b"not a graph").hexdigest())
    with pytest.raises(EfficientTrackError, match="ONNX Runtime cannot load the graph"):
        load_onnx_policy(folder)
    (folder / CONTRACT_FILE).write_text("{")
    with pytest.raises(EfficientTrackError, match="not a readable JSON file"):
        load_onnx_policy(folder)
    (folder / CONTRACT_FILE).unlink()
    with pytest.raises(EfficientTrackError, match="policy.json: no such file"):
        load_onnx_policy(folder)
    with pytest.raises(EfficientTrackError, match="threads must be an integer"):
        load_onnx_policy(exported, threads=0)


def test_the_guard_bound_comes_from_the_limits_not_the_export(exported):
    """The contract's max_adjust can only tighten the machine's bound: a tighter machine bound is enforced."""
    tight = GuardLimits(max_adjust=(1e-4,) * 4)
    runtime = OnnxRuntime(load_onnx_policy(exported), limits=tight)
    np.testing.assert_array_equal(runtime.max_adjust, 1e-4)
    runtime.start(np.zeros((1, 8)))
    sent = runtime.step(np.zeros((1, 8)), np.full((1, 3, 4), 0.1))
    assert sent.fallback[0] and runtime.counts["adjust_bound"][0] == 1
    np.testing.assert_array_equal(sent.q_ref, 0.1)


def test_an_export_that_differs_from_the_policy_is_not_written(logged, tmp_path, monkeypatch):
    monkeypatch.setattr(export_module, "PARITY_TOLERANCE", -1.0)
    with pytest.raises(EfficientTrackError, match="differs from the policy"):
        export_policy(logged[0], tmp_path / "out")
    assert list((tmp_path / "out").iterdir()) == []


def test_export_command(logged, tmp_path):
    checkpoint = save_policy(logged[0], tmp_path / "policy.pt", "ab" * 32)
    out = tmp_path / "export"

    def invoke(*args):
        return CliRunner().invoke(app, ["export", "--policy", str(checkpoint), "--out", *map(str, args)])

    result = invoke(out)
    assert result.exit_code == 0, result.output
    contract = json.loads((out / CONTRACT_FILE).read_text())
    assert contract["source"]["checkpoint"] == "policy.pt" and len(contract["source"]["weights_sha256"]) == 64
    assert contract["source"]["training_fingerprint"] == "ab" * 32
    result = invoke(out)
    assert isinstance(result.exception, EfficientTrackError) and "not empty" in str(result.exception)
    assert invoke(out, "--force").exit_code == 0
    (tmp_path / "afile").write_text("x")
    result = invoke(tmp_path / "afile")
    assert isinstance(result.exception, EfficientTrackError) and "is a file" in str(result.exception)


def test_a_checkpoint_saved_without_a_fingerprint_still_loads_and_exports(logged, tmp_path):
    checkpoint = save_policy(logged[0], tmp_path / "policy.pt")
    meta = json.loads(checkpoint.with_suffix(".json").read_text())
    assert meta.pop("training_fingerprint") is None  # not known here; an older checkpoint lacks the field altogether
    checkpoint.with_suffix(".json").write_text(json.dumps(meta))
    result = CliRunner().invoke(app, ["export", "--policy", str(checkpoint), "--out", str(tmp_path / "export")])
    assert result.exit_code == 0, result.output
    assert json.loads((tmp_path / "export" / CONTRACT_FILE).read_text())["source"]["training_fingerprint"] is None


EXTRA_LIBRARIES = tuple(EXTRAS)
"""What the core install leaves out: the libraries of pyproject.toml's extras (tests/test_wheel.py checks both)."""


def test_the_command_line_on_the_core_install_names_the_extra_a_command_needs_in_one_line(tmp_path):
    script = tmp_path / "cli.py"
    blocker = BLOCK_TORCH.replace('name == "torch" or name.startswith("torch.")', f'name.split(".")[0] in {EXTRA_LIBRARIES}')
    blocker = blocker.replace(
        """raise ModuleNotFoundError("No module named 'torch' (blocked by the test)")""",
        """raise ModuleNotFoundError(f"No module named {name!r} (blocked by the test)", name=name)""",
    )
    script.write_text(blocker + "from efficienttrack.__main__ import main\nmain()\n")
    env = {**os.environ, "PYTHONPATH": str(SRC)}

    def cli(*args):
        return subprocess.run([sys.executable, str(script), *args], capture_output=True, text=True, env=env, timeout=60)

    assert cli("--help").returncode == 0
    for args, extra in (
        (("export", "--policy", str(tmp_path / "policy.pt"), "--out", str(tmp_path / "export")), "train"),
        (("import-rosbag", str(tmp_path / "bag"), "--reference", "/ref", "--out", str(tmp_path / "records")), "ros"),
    ):
        done = cli(*args)
        assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
        assert done.stderr.count("\n") == 1 and f"pip install 'efficienttrack[{extra}]'" in done.stderr, done.stderr


def test_the_torch_free_runtime_given_a_checkpoint_says_to_export_it(tmp_path):
    (tmp_path / "policy.pt").write_bytes(b"PK\x03\x04")
    with pytest.raises(EfficientTrackError, match=r"policy.pt: a torch checkpoint, .*\(efficienttrack export --policy"):
        load_onnx_policy(tmp_path / "policy.pt")

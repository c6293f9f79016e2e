"""The open loop's model and policy, open-loop EfficientTrack and SuperTrack (closed and open loop), at the quick size."""

import dataclasses
import json

import numpy as np
import pytest
import torch

from efficienttrack.baselines.agent import policy_act
from efficienttrack.baselines.curve import CURVE_FILE, training_run
from efficienttrack.baselines.openloop import OPEN_PRESETS, imitate, pass_counts, train_efficienttrack_open
from efficienttrack.baselines.resume import STATE_FILE
from efficienttrack.baselines.supertrack import SUPERTRACK_PRESETS, train_supertrack
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.data.cycles import generate_references
from efficienttrack.data.dataset import Sequences
from efficienttrack.data.metrics import compute_metrics
from efficienttrack.data.references import Reference
from efficienttrack.envs import evaluate
from efficienttrack.learn.checkpoints import load_tensors
from efficienttrack.learn.dynamics import PlantModel, model_error, train_model
from efficienttrack.learn.policy import PWMPolicy, train_policy
from efficienttrack.learn.settings import MODEL_PRESETS, POLICY_PRESETS
from efficienttrack.systems.pd import PDGains
from efficienttrack.systems.protocol import BatchedSystem
from efficienttrack.systems.spec import SystemSpec, close_loop
from efficienttrack.workflow.collect import CollectConfig, run_pass

torch.set_num_threads(1)


def short_refs(count, steps, seed=0):
    """Generated loading cycles cut to ``steps`` positions (fast episodes on the built-in xe75)."""
    return [Reference(f"{r.name}_short", r.q[:steps]) for r in generate_references(count, seed=seed)]


class VelocityPlant:
    """A toy PWM plant: each joint's velocity is 2 rad/s per 1000 PWM, reached at once (an integrator)."""

    batched = True
    dt = 0.05

    def reset(self, q0):
        self.q = np.array(q0, dtype=np.float64)
        return np.concatenate([self.q, np.zeros_like(self.q)], axis=-1)

    def step(self, u):
        qd = 2.0 * np.asarray(u) / 1000.0
        self.q = self.q + self.dt * qd
        return np.concatenate([self.q, qd], axis=-1)


def sine_refs(n, steps=60):
    t = np.arange(steps)[:, None] * 0.05
    return [Reference(f"sine_{i}", 0.3 * np.sin((1.5 + 0.3 * i) * t + np.arange(4) + i)) for i in range(n)]


def test_open_windows_hold_the_commands_and_start_at_rest():
    plant = BatchedSystem(VelocityPlant(), "toy")
    records = run_pass(close_loop(plant, PD, "toy"), sine_refs(1, 10), CollectConfig(sigma_max=0.0), 0)
    data = Sequences(records, history=3, future=2, channel="u")
    window = data.window(data.starts(1)[:2], horizon=1)
    u = records[0].u / 1000
    assert torch.equal(window.qref_hist[0], torch.zeros(3, 4))  # u_{−3..−1}: at rest
    np.testing.assert_allclose(window.qref_future[:, 0].numpy(), u[:2], rtol=1e-6)  # u_t
    np.testing.assert_allclose(window.qref_hist[1, -1].numpy(), u[0], rtol=1e-6)  # u_{t−1}
    with pytest.raises(EfficientTrackError, match="PWM u"):
        Sequences([dataclasses.replace(records[0], u=None)], history=3, future=2, channel="u")


PD = PDGains(kp=(2000.0,) * 4, kd=(0.0,) * 4, sign=(1.0,) * 4, c=0.0)
"""A P controller on the toy plant: u = 2000 e, so it closes 20 % of the error a step and lags a moving reference."""


def test_plant_model_error_falls_with_training_on_xe75_data():
    records = run_pass(SystemSpec().open(), short_refs(3, 120), CollectConfig(), 0)
    cfg = dataclasses.replace(MODEL_PRESETS["tiny"], horizon=4, history=3, steps=1)
    before = model_error(train_model(cfg, records, "cpu", 0, progress=False, network=PlantModel).model, records, 10)
    # 100 steps: about 0.12 of the error before at seeds 0-2 (250 steps: 0.09)
    trained = train_model(dataclasses.replace(cfg, steps=100), records, "cpu", 0, progress=False, network=PlantModel).model
    after = model_error(trained, records, 10)
    assert after.mpe_deg < 0.5 * before.mpe_deg


def test_pwm_policy_through_its_model_tracks_better_than_the_p_controller_on_a_toy_plant():
    plant = BatchedSystem(VelocityPlant(), "toy")
    closed = close_loop(plant, PD, "toy")
    refs = sine_refs(6)
    noisy = CollectConfig(sigma_max=0.3, noise_ratio=(1.0, 0.0))  # the plant model needs commands not fixed by the state
    records = [r for k in range(3) for r in run_pass(closed, refs, noisy, k)]
    # 100 steps each: about 0.1 of the P controller's error at seeds 0-2 (300 steps: 0.045; below 60 it breaks down)
    model_cfg = dataclasses.replace(MODEL_PRESETS["tiny"], horizon=4, history=2, steps=100)
    g_theta = train_model(model_cfg, records, "cpu", 0, progress=False, network=PlantModel).model
    policy_cfg = dataclasses.replace(POLICY_PRESETS["tiny"], horizon=4, steps=100, k_smooth=0.01)
    init = imitate(policy_cfg, records, 100, 0)
    pi_phi = train_policy(policy_cfg, g_theta, records, "cpu", 0, progress=False, init=init, network=PWMPolicy).policy
    pd_mae = compute_metrics(evaluate(lambda obs: np.zeros((len(obs), 4)), refs, "closed", closed))["mae_deg"]
    imitation_mae = compute_metrics(evaluate(policy_act(init, "open"), refs, "open", plant))["mae_deg"]
    ours_mae = compute_metrics(evaluate(policy_act(pi_phi, "open"), refs, "open", plant))["mae_deg"]
    zero_mae = compute_metrics(evaluate(lambda obs: np.zeros((len(obs), 4)), refs, "open", plant))["mae_deg"]
    assert ours_mae < 0.4 * pd_mae and ours_mae < 0.4 * imitation_mae and ours_mae < 0.1 * zero_mae


def test_pwm_policy_cannot_drive_the_closed_loop_model():
    with pytest.raises(EfficientTrackError, match="PWMPolicy"):
        policy_act(PWMPolicy(POLICY_PRESETS["tiny"]), "closed")


REFS = short_refs(6, 80)
TRAIN, TEST = REFS[:4], REFS[4:]
"""Four short training references (316 steps a pass) and two test ones."""
TINY_OPEN = OPEN_PRESETS["tiny"]
OPEN_SETTINGS = dataclasses.replace(
    TINY_OPEN,
    model=dataclasses.replace(TINY_OPEN.model, steps=30),
    policy=dataclasses.replace(TINY_OPEN.policy, steps=20),
    imitation_steps=20,
)
"""Open-loop EfficientTrack's quick settings with a third of their training steps: the curves are tested, not the policy."""
TINY_SUPERTRACK = SUPERTRACK_PRESETS["tiny"]
SUPERTRACK_SETTINGS = dataclasses.replace(
    TINY_SUPERTRACK,
    model=dataclasses.replace(TINY_SUPERTRACK.model, steps=10),
    policy=dataclasses.replace(TINY_SUPERTRACK.policy, steps=10),
    steps_per_iteration=300,
)
"""SuperTrack's quick settings, 300 interaction steps an iteration and half the training steps."""


@pytest.fixture(scope="module")
def open_run(tmp_path_factory):
    """Open-loop EfficientTrack (``OPEN_SETTINGS``), seed 0, 1,000 steps (two pass counts), uninterrupted:
    ``(curve, folder)``."""
    folder = tmp_path_factory.mktemp("open") / "a"
    run = training_run("open", SystemSpec(), TRAIN, TEST, 1000, 0, folder)
    return train_efficienttrack_open(run, preset=OPEN_SETTINGS), folder


@pytest.fixture(scope="module")
def supertrack_run(tmp_path_factory):
    """``supertrack_run(loop)``: SuperTrack (``SUPERTRACK_SETTINGS``), seed 3, 700 steps measured at 300 and 700,
    uninterrupted, run once per loop for the module: ``(curve, folder)``."""
    runs = {}

    def run(loop):
        if loop not in runs:
            folder = tmp_path_factory.mktemp(f"supertrack_{loop}") / "a"
            run = training_run(loop, SystemSpec(), TRAIN, TEST, 700, 3, folder, eval_at=[300, 700])
            curve = train_supertrack(run, preset=SUPERTRACK_SETTINGS)
            runs[loop] = curve, folder
        return runs[loop]

    return run


def test_open_loop_efficienttrack_quick_curve_and_determinism(tmp_path, open_run):
    assert pass_counts(1000, 316) == [1, 2]
    curve, folder = open_run
    assert [p["passes"] for p in curve] == [1, 2] and [p["interaction_steps"] for p in curve] == [316, 632]
    model, policy = OPEN_SETTINGS.model, OPEN_SETTINGS.policy  # each pass count's trainings: model, imitation, policy
    samples = model.steps * model.batch_size + (OPEN_SETTINGS.imitation_steps + policy.steps) * policy.batch_size
    assert [p["gradient_samples"] for p in curve] == [samples, samples]
    assert all(np.isfinite(p["metrics"]["mae_deg"]) and p["wall_seconds"] > 0 for p in curve)
    saved = json.loads((folder / CURVE_FILE).read_text())
    assert saved["method"] == "efficienttrack" and saved["loop"] == "open" and len(saved["curve"]) == 2
    again = train_efficienttrack_open(training_run("open", SystemSpec(), TRAIN, TEST, 400, 0, tmp_path / "b"), OPEN_SETTINGS)
    assert again[0]["metrics"] == curve[0]["metrics"]


@pytest.mark.slow
def test_an_interrupted_open_loop_efficienttrack_run_keeps_its_finished_pass_counts(
    tmp_path, monkeypatch, interrupt_at, open_run
):
    def run(folder, seed=0, budget=1000):
        return train_efficienttrack_open(training_run("open", SystemSpec(), TRAIN, TEST, budget, seed, folder), OPEN_SETTINGS)

    interrupt_at(632)  # killed when it would measure two passes
    with pytest.raises(KeyboardInterrupt):
        run(tmp_path)
    monkeypatch.undo()
    before = json.loads((tmp_path / CURVE_FILE).read_text())["curve"]
    assert [p["passes"] for p in before] == [1]
    resumed = run(tmp_path)
    assert [p["passes"] for p in resumed] == [1, 2] and resumed[0] == before[0]  # one pass kept, not trained again
    assert resumed[1]["metrics"] == open_run[0][1]["metrics"]  # as the uninterrupted run (the same seed and budget)
    assert run(tmp_path, seed=1, budget=400)[0]["metrics"] != resumed[0]["metrics"]  # another run starts over


@pytest.mark.parametrize("loop", ["closed", "open"])
def test_supertrack_quick_curve_and_determinism(tmp_path, loop, supertrack_run):
    curve, folder = supertrack_run(loop)
    assert [p["iterations"] for p in curve] == [1, 3] and curve[-1]["interaction_steps"] >= 700
    model, policy = SUPERTRACK_SETTINGS.model, SUPERTRACK_SETTINGS.policy  # both trainings' windows, every iteration
    assert [p["gradient_samples"] for p in curve] == [k * (model.steps * model.batch_size + policy.steps * policy.batch_size)
                                                       for k in (1, 3)]  # fmt: skip
    assert all(np.isfinite(p["metrics"]["mae_deg"]) for p in curve)
    saved = json.loads((folder / CURVE_FILE).read_text())
    assert saved["method"] == "supertrack" and saved["loop"] == loop and len(saved["curve"]) == 2
    again = train_supertrack(training_run(loop, SystemSpec(), TRAIN, TEST, 300, 3, tmp_path / "b"), preset=SUPERTRACK_SETTINGS)
    assert again[0]["metrics"] == curve[0]["metrics"]


def test_an_interrupted_supertrack_run_resumes_as_if_uninterrupted(tmp_path, monkeypatch, interrupt_at, supertrack_run):
    def run(folder, seed=3):
        spec = training_run("closed", SystemSpec(), TRAIN, TEST, 700, seed, folder, [300, 700])
        return train_supertrack(spec, SUPERTRACK_SETTINGS, save_every_seconds=0)

    uninterrupted, _ = supertrack_run("closed")  # saved its state less often; seeded, the same curve
    interrupt_at(700)
    with pytest.raises(KeyboardInterrupt):
        run(tmp_path / "b")
    monkeypatch.undo()
    assert load_tensors(tmp_path / "b" / STATE_FILE)["iteration"] == 2
    before = json.loads((tmp_path / "b" / CURVE_FILE).read_text())["curve"]
    with pytest.raises(EfficientTrackError, match="training_state.pt: the training state of another run"):
        run(tmp_path / "b", seed=4)
    resumed = run(tmp_path / "b")
    assert resumed[0] == before[0]  # kept as measured (its wall time too), not measured again
    assert [p["metrics"] for p in resumed] == [p["metrics"] for p in uninterrupted]
    assert [p["iterations"] for p in resumed] == [1, 3] and not (tmp_path / "b" / STATE_FILE).exists()
    (tmp_path / "c").mkdir()
    (tmp_path / "c" / STATE_FILE).write_bytes(b"not a state")
    with pytest.raises(EfficientTrackError, match="training_state.pt: refused to load"):
        run(tmp_path / "c")


def test_bad_input_is_refused(tmp_path):
    with pytest.raises(EfficientTrackError, match="open loop only"):
        train_efficienttrack_open(training_run("closed", SystemSpec(), TRAIN, TEST, 1000, 0, tmp_path), preset="tiny")
    with pytest.raises(EfficientTrackError, match="PWM-level plant"):
        train_efficienttrack_open(training_run("open", SystemSpec(system="learned"), TRAIN, TEST, 1000, 0, tmp_path))
    with pytest.raises(EfficientTrackError, match="less than one collection pass"):
        train_efficienttrack_open(training_run("open", SystemSpec(), TRAIN, TEST, 100, 0, tmp_path), preset="tiny")
    with pytest.raises(EfficientTrackError, match="PWM-level plant"):
        train_supertrack(training_run("open", SystemSpec(system="learned"), TRAIN, TEST, 1000, 0, tmp_path))
    with pytest.raises(EfficientTrackError, match="loop"):
        train_supertrack(training_run("sideways", SystemSpec(), TRAIN, TEST, 1000, 0, tmp_path))
    with pytest.raises(EfficientTrackError, match="preset"):
        train_supertrack(training_run("closed", SystemSpec(), TRAIN, TEST, 1000, 0, tmp_path), preset="huge")
    with pytest.raises(EfficientTrackError, match="budget"):
        train_supertrack(training_run("closed", SystemSpec(), TRAIN, TEST, 0, 0, tmp_path))
    with pytest.raises(EfficientTrackError, match="run: expected a TrainingRun"):
        train_supertrack("closed")
    with pytest.raises(EfficientTrackError, match=r"OpenLoopSettings.imitation_steps must be an integer in \[0, 10000000\]"):
        dataclasses.replace(OPEN_PRESETS["tiny"], imitation_steps=-1)

"""Config files refuse non-finite numbers and sizes beyond their documented bounds, naming the field and the bound."""

import dataclasses

import gymnasium
import pytest
import torch

from efficienttrack.core.configfile import MAX_CONFIG_BYTES
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.joints import MAX_HORIZON
from efficienttrack.data.cycles import generate_references
from efficienttrack.learn import nets
from efficienttrack.learn.dynamics import ClosedLoopModel, model_error, train_model
from efficienttrack.learn.nets import check_training_memory, training_bytes
from efficienttrack.learn.settings import (
    MAX_BATCH_SIZE,
    MAX_EPOCHS,
    MAX_HIDDEN,
    MAX_LAYERS,
    MAX_STEPS,
    MODEL_PRESETS,
    POLICY_PRESETS,
    ModelConfig,
    PolicyConfig,
)
from efficienttrack.systems.limits import GuardLimits
from efficienttrack.workflow.collect import MAX_PASSES, CollectConfig
from efficienttrack.workflow.config import MAX_ROUNDS, PRESETS, RunConfig, load_config
from test_cli import invoke, refused
from test_dynamics import lag_records

# ------------------------------------------------------------------------------------- non-finite numbers


@pytest.mark.parametrize(
    ("text", "field"),
    [
        ("model:\n  grad_clip: .nan\n", "grad_clip"),
        ("model:\n  lr: .inf\n", "lr"),
        ("policy:\n  gamma: .nan\n", "gamma"),
        ("policy:\n  max_adjust: [0.1, 0.1, .nan, 0.1]\n", "max_adjust"),
        ("collect:\n  sigma_max: -.inf\n", "sigma_max"),
        ("warm_budget: .nan\n", "warm_budget"),
    ],
)
def test_a_yaml_config_refuses_nan_and_inf(tmp_path, text, field):
    path = tmp_path / "cfg.yaml"
    path.write_text(text)
    with pytest.raises(EfficientTrackError, match=rf"cfg.yaml.*{field}"):
        load_config(path)


def test_a_json_config_refuses_nan_and_infinity(tmp_path):
    path = tmp_path / "cfg.json"
    for value in ("NaN", "Infinity", "1e999"):
        path.write_text('{"model": {"grad_clip": ' + value + "}}")
        with pytest.raises(EfficientTrackError, match="model.grad_clip must be a finite number"):
            load_config(path)


def test_a_key_given_twice_is_refused_in_configs_and_limits_files(tmp_path):
    """YAML and JSON keep the last of two equal keys: a second ``model:`` or ``accept_implausible`` would win silently."""
    cases = {
        "cfg.yaml": ("model:\n  lr: 1e-3\nmodel:\n  lr: 1e-2\n", load_config, r"the key 'model' is given twice \(line 3\)"),
        "cfg.json": ('{"seed": 1, "seed": 2}', load_config, "the key 'seed' is given twice"),
        "lim.yaml": ("accept_implausible: false\nmax_adjust: [3, 3, 3, 3]\naccept_implausible: true\n", GuardLimits.load,
                     "the key 'accept_implausible' is given twice"),
    }  # fmt: skip
    for name, (text, load, message) in cases.items():
        (tmp_path / name).write_text(text)
        with pytest.raises(EfficientTrackError, match=rf"{name}: cannot read the config \(.*{message}"):
            load(tmp_path / name)


def test_a_config_file_past_its_size_cap_is_refused_before_it_is_read(tmp_path):
    path = tmp_path / "lim.yaml"
    path.write_text("q_min: [" + "0, " * (MAX_CONFIG_BYTES // 3) + "0]")
    with pytest.raises(EfficientTrackError, match=r"lim.yaml: cannot read the config \([\d,]+ bytes, more than the 1,048,576"):
        GuardLimits.load(path)


def test_a_config_built_in_code_refuses_an_infinite_grad_clip():
    with pytest.raises(EfficientTrackError, match="ModelConfig.grad_clip must be a finite number"):
        ModelConfig(grad_clip=float("inf"))
    with pytest.raises(EfficientTrackError, match="PolicyConfig.weight_decay must be a finite number"):
        PolicyConfig(weight_decay=float("nan"))


# ------------------------------------------------------------------------------------------------ sizes


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("policy:\n  horizon: 100000\n", f"policy.horizon must be an integer in [2, {MAX_HORIZON}]"),
        ("model:\n  horizon: 100000\n", f"model.horizon must be an integer in [1, {MAX_HORIZON}]"),
        ("model:\n  history: 100000\n", f"model.history must be an integer in [1, {MAX_HORIZON}]"),
        ("policy:\n  lr: 1.0e300\n", "policy.lr must be a finite number in (0, 10]"),
        ("model:\n  weight_decay: 1.0e300\n", "model.weight_decay must be a finite number in [0, 100]"),
        ("model:\n  hidden: 1000000000\n", f"model.hidden must be an integer in [1, {MAX_HIDDEN}]"),
        ("model:\n  hidden: 1e9\n", "model.hidden must be an integer"),
        ("policy:\n  layers: 1000\n", f"policy.layers must be an integer in [1, {MAX_LAYERS}]"),
        ("policy:\n  batch_size: 10000000\n", f"policy.batch_size must be an integer in [1, {MAX_BATCH_SIZE}]"),
        ("model:\n  steps: 1000000000000\n", f"model.steps must be an integer in [1, {MAX_STEPS}]"),
        ("model:\n  steps: null\n  epochs: 100000000\n", f"model.epochs must be an integer in [1, {MAX_EPOCHS}]"),
        ("collect:\n  passes: 100000\n", f"collect.passes must be an integer in [1, {MAX_PASSES}]"),
        ("rounds: 100000\n", f"rounds must be an integer in [1, {MAX_ROUNDS}]"),
    ],
)
def test_sizes_beyond_their_bound_are_refused_naming_field_and_bound(tmp_path, text, message):
    path = tmp_path / "cfg.yaml"
    path.write_text(text)
    with pytest.raises(EfficientTrackError, match="cfg.yaml") as caught:
        load_config(path)
    assert message in str(caught.value)


def test_sizes_given_in_code_are_checked_for_type_and_bound():
    with pytest.raises(EfficientTrackError, match="ModelConfig.hidden must be an integer"):
        ModelConfig(hidden=1e9)
    with pytest.raises(EfficientTrackError, match="CollectConfig|collect.passes"):
        CollectConfig(passes=2.5)
    with pytest.raises(EfficientTrackError, match="RunConfig.rounds"):
        RunConfig(rounds=MAX_ROUNDS + 1)


def test_the_presets_lie_well_inside_the_bounds():
    for cfg in (*MODEL_PRESETS.values(), *POLICY_PRESETS.values()):
        assert cfg.hidden * 8 <= MAX_HIDDEN and cfg.layers * 8 <= MAX_LAYERS and cfg.horizon * 10 <= MAX_HORIZON
        assert cfg.batch_size * 8 <= MAX_BATCH_SIZE
    assert all(preset.collect.passes * 10 <= MAX_PASSES for preset in PRESETS.values())


def test_epochs_making_too_many_steps_are_refused_when_the_windows_are_known():
    cfg = dataclasses.replace(MODEL_PRESETS["paper"], epochs=MAX_EPOCHS)
    assert cfg.total_steps(2048 * 10) == 10 * MAX_EPOCHS
    with pytest.raises(EfficientTrackError, match=rf"ModelConfig.epochs: .* more than the {MAX_STEPS} allowed"):
        cfg.total_steps(2048 * 1000)


def test_cli_steps_beyond_the_bound_is_a_one_line_error(tmp_path):
    from efficienttrack.data.records import save_records

    save_records(lag_records(n=1, T=40), tmp_path / "data")
    result = invoke("train-model", "--data", tmp_path / "data", "--out", tmp_path / "m.pt", "--steps", 10**12)
    refused(result, f"ModelConfig.steps must be an integer in [1, {MAX_STEPS}]")
    assert not (tmp_path / "m.pt").exists()


def test_model_error_steps_are_bounded():
    with pytest.raises(EfficientTrackError, match=f"model_error.steps must be ≤ {MAX_HORIZON}"):
        model_error(ClosedLoopModel(MODEL_PRESETS["tiny"]), lag_records(n=1, T=40), steps=100_000)


# ----------------------------------------------------------------------------------------------- memory


def test_memory_estimate_is_a_few_gib_for_the_paper_and_refuses_what_cannot_fit():
    paper_model, paper_policy = MODEL_PRESETS["paper"], POLICY_PRESETS["paper"]
    estimate = training_bytes(paper_policy.batch_size, paper_policy.horizon, [paper_policy, paper_model])
    assert 1 * 2**30 < estimate < 16 * 2**30
    huge = ModelConfig(hidden=MAX_HIDDEN, layers=MAX_LAYERS, horizon=MAX_HORIZON, history=None, batch_size=MAX_BATCH_SIZE)
    with pytest.raises(EfficientTrackError, match=r"ModelConfig: a training step needs about .* GiB .* lower batch_size"):
        check_training_memory("ModelConfig", huge.batch_size, huge.horizon, [huge], torch.device("cpu"))


def test_training_checks_the_memory_before_any_work(monkeypatch):
    monkeypatch.setattr(nets, "device_memory", lambda device: 1024)
    with pytest.raises(EfficientTrackError, match="more than the 0.0 GiB of cpu"):
        train_model(MODEL_PRESETS["tiny"], lag_records(n=1, T=40), "cpu", progress=False)


def test_huge_sizes_are_refused_before_any_allocation(tmp_path):
    from efficienttrack.envs import CLOSED_LOOP_ID

    refused(
        invoke("refs", "generate", "--n", 10**9, "--out", tmp_path / "refs"), "n: need 1 to 10,000 references, got 1000000000"
    )
    assert not (tmp_path / "refs").exists()
    refs = generate_references(1, seed=0)
    with pytest.raises(EfficientTrackError, match=f"history and future must be 1 to {MAX_HORIZON} steps"):
        gymnasium.make(CLOSED_LOOP_ID, refs=refs, history=10**7)
    with pytest.raises(EfficientTrackError, match="seed: a seed must be an integer"):
        generate_references(1, seed=-1)

"""The settings tree: one validator however it is made, ``--set`` on every command that trains, ``config show``."""

import dataclasses
import json
import re
import subprocess
import sys

import pytest
import yaml

from efficienttrack.baselines.supertrack import SuperTrackSettings
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.settings import check_fields, parse_override, plain_form, setting, settings_from_dict, settings_table
from efficienttrack.learn import dynamics, policy
from efficienttrack.learn.dynamics import ClosedLoopModel, save_model
from efficienttrack.learn.policy import AdjustmentPolicy, save_policy
from efficienttrack.learn.settings import MODEL_PRESETS, POLICY_PRESETS, ModelConfig, PolicyConfig
from efficienttrack.study.methods import METHODS, changed_settings, preset_settings, settable
from efficienttrack.workflow import next_round, pipeline
from efficienttrack.workflow.collect import CollectConfig
from efficienttrack.workflow.config import PRESETS, RunConfig, apply_overrides, from_dict, load_config
from test_cli import invoke, refused
from test_dynamics import lag_records


class Captured(Exception):
    """Raised by a patched library function: carries the settings the command handed it."""


def capture():
    """A stand-in for a library function: raises :class:`Captured` with the arguments it was called with."""

    def stand_in(*args, **kwargs):
        raise Captured(args, kwargs)

    return stand_in


def captured(result):
    assert isinstance(result.exception, Captured), result.output
    return result.exception.args


def test_the_library_defaults_are_the_cpu_preset():
    assert RunConfig() == PRESETS["cpu"]
    assert ModelConfig() == MODEL_PRESETS["cpu"] and PolicyConfig() == POLICY_PRESETS["cpu"]
    assert RunConfig().model.history == 5


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: RunConfig(device="gpu"), "RunConfig.device must be one of auto, cpu, cuda, cuda:N, got 'gpu'"),
        (lambda: RunConfig(rounds=0), "RunConfig.rounds must be an integer in [1, 100], got 0"),
        (lambda: ModelConfig(lr=1e300), "ModelConfig.lr must be a finite number in (0, 10], got 1e+300"),
        (lambda: PolicyConfig(horizon=1), "PolicyConfig.horizon must be an integer in [2, 400], got 1"),
        (lambda: CollectConfig(passes=True), "CollectConfig.passes must be an integer in [1, 1000], got True"),
        (lambda: CollectConfig(noise_ratio=(0, 0)), "CollectConfig.noise_ratio: needs a weight > 0"),
        (lambda: SuperTrackSettings(noise_rho=1), "SuperTrackSettings.noise_rho must be a finite number in [0, 1), got 1"),
    ],
)
def test_python_refuses_what_a_file_refuses(make, message):
    with pytest.raises(EfficientTrackError) as caught:
        make()
    assert str(caught.value) == message or message in str(caught.value)


def test_a_value_given_in_python_is_converted_as_from_a_file():
    cfg = PolicyConfig(max_adjust=[0.1, 0.2, 0.3, 0.4], lr=1)
    assert cfg.max_adjust == (0.1, 0.2, 0.3, 0.4) and isinstance(cfg.lr, float)
    assert cfg == PolicyConfig.from_dict({"max_adjust": [0.1, 0.2, 0.3, 0.4], "lr": 1})


def test_the_device_a_file_gives_is_refused_as_in_python(tmp_path):
    (tmp_path / "c.yaml").write_text("device: gpu\n")
    with pytest.raises(EfficientTrackError, match=r"c.yaml: device must be one of auto, cpu, cuda, cuda:N, got 'gpu'"):
        load_config(tmp_path / "c.yaml")


def test_a_config_files_seed_governs_collection_and_training(tmp_path):
    (tmp_path / "c.yaml").write_text("seed: 1\n")
    cfg = load_config(tmp_path / "c.yaml", PRESETS["tiny"])
    assert cfg.seed == 1 and cfg.collect.seed == 1
    assert dataclasses.replace(cfg, seed=4).collect.seed == 4
    (tmp_path / "both.yaml").write_text("seed: 1\ncollect:\n  seed: 1\n")
    assert load_config(tmp_path / "both.yaml").collect.seed == 1
    (tmp_path / "other.yaml").write_text("seed: 1\ncollect:\n  seed: 2\n")
    with pytest.raises(EfficientTrackError, match="collect.seed is 2 but seed is 1"):
        load_config(tmp_path / "other.yaml")


def test_a_config_files_seed_reaches_the_collection_of_a_run(tmp_path, monkeypatch):
    """End to end through `run`: the noise of the records is drawn with the file's seed, as the training is."""
    from efficienttrack.data.references import save_references
    from toy_system import sine_refs

    monkeypatch.setattr(pipeline, "collect", capture())
    save_references(sine_refs([40, 40]), tmp_path / "refs")
    (tmp_path / "c.yaml").write_text("seed: 3\n")
    args = ("run", "--train-refs", tmp_path / "refs", "--test-refs", tmp_path / "refs", "--out", tmp_path / "out")
    result = invoke(*args, "--system", "toy_system:make", "--preset", "tiny", "--config", tmp_path / "c.yaml")
    (_, _, collect_cfg, *_), _ = captured(result)
    assert collect_cfg.seed == 3


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("model.history=5", {"model": {"history": 5}}),
        ("model.history=null", {"model": {"history": None}}),
        ("policy.lr=1e-4", {"policy": {"lr": 1e-4}}),
        ("collect.noise_ratio=[9, 3]", {"collect": {"noise_ratio": [9, 3]}}),
        ("device=cpu", {"device": "cpu"}),
    ],
)
def test_an_override_is_read_as_yaml_at_its_path(text, expected):
    assert parse_override(text) == expected


def test_overrides_apply_in_order_and_are_checked_naming_the_override():
    cfg = apply_overrides(PRESETS["tiny"], ["model.history=2", "model.history=3", "seed=7", "collect.noise_ratio=[9, 3]"])
    assert cfg.model.history == 3 and cfg.seed == 7 and cfg.collect.seed == 7 and cfg.collect.noise_ratio == (9.0, 3.0)
    assert cfg.policy == PRESETS["tiny"].policy
    for text, message in [
        ("model.histroy=3", "--set model.histroy=3: unknown ModelConfig field(s) model.histroy"),
        ("model.history=0", "--set model.history=0: model.history must be an integer in [1, 400]"),
        ("model=3", "--set model=3: model expected a mapping of ModelConfig fields"),
        ("history", "--set 'history': expected section.field=value"),
        ("model.lr=[1", "--set 'model.lr=[1': the value is not valid YAML"),
    ]:
        with pytest.raises(EfficientTrackError) as caught:
            apply_overrides(PRESETS["tiny"], [text])
        assert message in str(caught.value), str(caught.value)


def test_the_tree_lists_every_leaf_with_its_bounds():
    rows = {path: (value, bounds) for path, value, bounds in settings_table(RunConfig())}
    assert rows["model.lr"] == (3e-3, "in (0, 10]")
    assert rows["model.history"] == (5, "in [1, 400] or null")
    assert rows["policy.max_adjust"][1] == "4 numbers, each > 0"
    assert rows["device"] == ("auto", "one of auto, cpu, cuda, cuda:N")
    assert (
        len(rows)
        == len(dataclasses.fields(CollectConfig))
        + len(dataclasses.fields(ModelConfig))
        + len(dataclasses.fields(PolicyConfig))
        + len(dataclasses.fields(RunConfig))
        - 3
    )


def test_the_closed_loop_networks_ramp_up_to_their_higher_rate_and_those_measured_before_keep_their_rate():
    from efficienttrack.baselines.openloop import OPEN_PRESETS
    from efficienttrack.baselines.supertrack import SUPERTRACK_PRESETS

    own = {"model": MODEL_PRESETS, "policy": POLICY_PRESETS}
    for part, presets in own.items():
        cpu = getattr(PRESETS["cpu"], part)
        assert (cpu.lr, cpu.warmup) == (3e-3, 0.1) and getattr(PRESETS["fastset"], part) == cpu, part
        kept = [presets["paper"], presets["tiny"]]
        kept += [getattr(baseline[name], part) for baseline in (SUPERTRACK_PRESETS, OPEN_PRESETS) for name in ("cpu", "tiny")]
        assert all(cfg.warmup == 0 for cfg in kept), part  # SuperTrack, the open loop and the paper as they were measured
        assert getattr(SUPERTRACK_PRESETS["cpu"], part).lr == getattr(OPEN_PRESETS["cpu"], part).lr == 1e-3, part


@pytest.mark.parametrize("name", list(PRESETS))
def test_config_show_prints_a_file_that_config_reads_back(name, tmp_path):
    result = invoke("config", "show", name, "--set", "model.hidden=17", "--set", "seed=5")
    assert result.exit_code == 0, result.output
    assert "  hidden: 17" in result.output and "# in (0, 10]" in result.output
    (tmp_path / "shown.yaml").write_text(result.output)
    expected = apply_overrides(PRESETS[name], ["model.hidden=17", "seed=5"])
    assert load_config(tmp_path / "shown.yaml", PRESETS["cpu"]) == expected
    assert from_dict(expected.to_dict(), stored=True) == expected


def test_config_show_refuses_an_unknown_preset():
    refused(invoke("config", "show", "huge"), "--preset 'huge': unknown")


@pytest.mark.parametrize("method", settable())
def test_config_show_lists_every_study_methods_settings_as_method_set_reads_them(method):
    result = invoke("config", "show", "tiny", "--method", method)
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    assert lines[0] == f"# {method} settings of the study's preset tiny (study --method-set {method}.FIELD=VALUE)"
    shown = yaml.safe_load(result.output)
    assert changed_settings(method, "tiny", [f"{method}.{key}={json.dumps(value)}" for key, value in shown.items()]) == (
        preset_settings(method, "tiny")
    )  # every field shown is one --method-set takes, at the preset's value


def sections(settings):
    """A settings object and every settings dataclass nested in it."""
    yield settings
    for spec in dataclasses.fields(settings):
        if dataclasses.is_dataclass(value := getattr(settings, spec.name)):
            yield from sections(value)


@pytest.mark.parametrize("method", settable())
def test_every_methods_settings_go_through_the_one_validator(method):
    if not METHODS[method].available():
        pytest.skip(f"{method} needs {', '.join(METHODS[method].requires)}")
    for section in sections(preset_settings(method, "tiny")):
        owner = type(section).__name__
        for spec in dataclasses.fields(section):
            assert spec.metadata.get("bounds") is not None, f"{owner}.{spec.name} is not made with setting()"
            with pytest.raises(EfficientTrackError, match=f"^{re.escape(owner)}\\.{spec.name} must be "):
                dataclasses.replace(section, **{spec.name: object()})  # the wrong type: refused by check_fields


def test_config_show_of_a_method_without_settings_or_with_run_options_is_refused():
    refused(invoke("config", "show", "--method", "pd"), "--method pd: has no settings; methods with settings: efficienttrack")
    refused(invoke("config", "show", "--method", "dqn"), "--method dqn: unknown")
    refused(invoke("config", "show", "--method", "efficienttrack-rounds"), "takes the run's settings: efficienttrack config")
    refused(invoke("config", "show", "--method", "sac", "--set", "seed=1"), "takes no --config or --set")


@pytest.fixture
def data(tmp_path):
    from efficienttrack.data.records import save_records

    save_records(lag_records(n=2, T=40), tmp_path / "data")
    return tmp_path / "data"


def test_set_reaches_train_model(data, tmp_path, monkeypatch):
    monkeypatch.setattr(dynamics, "train_model", capture())
    result = invoke("train-model", "--data", data, "--out", tmp_path / "m.pt", "--preset", "tiny", "--set", "model.hidden=9",
                    "--set", "seed=4", "--set", "device=cpu")  # fmt: skip
    (cfg, _, device, seed, *_), _ = captured(result)
    assert cfg == dataclasses.replace(MODEL_PRESETS["tiny"], hidden=9) and (device, seed) == ("cpu", 4)


def test_set_reaches_train_policy(data, tmp_path, monkeypatch):
    save_model(ClosedLoopModel(MODEL_PRESETS["tiny"]), tmp_path / "m.pt")
    monkeypatch.setattr(policy, "train_policy", capture())
    (tmp_path / "c.yaml").write_text("policy:\n  k_smooth: 0.5\n")
    args = ("train-policy", "--model", tmp_path / "m.pt", "--data", data, "--out", tmp_path / "p.pt", "--preset", "tiny")
    result = invoke(*args, "--config", tmp_path / "c.yaml", "--set", "policy.gamma=0.9", "--seed", "2")
    (cfg, _, _, device, seed, *_), _ = captured(result)
    assert cfg == dataclasses.replace(POLICY_PRESETS["tiny"], k_smooth=0.5, gamma=0.9) and (device, seed) == ("auto", 2)


def test_a_value_at_a_fields_earlier_default_survives_the_overrides_and_options_after_it(tmp_path, monkeypatch):
    # a setting written back as its earlier default (``before``) by to_dict was read back as today's default
    cfg = apply_overrides(PRESETS["tiny"], ["policy.imagined_share=0", "round_warmup=0", "rounds=4"])
    assert (cfg.policy.imagined_share, cfg.round_warmup, cfg.rounds) == (0, 0, 4)
    calls = []
    monkeypatch.setattr(pipeline, "demo", lambda out, cfg, console, max_plots: calls.append(cfg))
    given = ("--set", "policy.imagined_share=0", "--set", "round_warmup=0", "--seed", "3", "--rounds", "2")
    assert invoke("demo", "--out", tmp_path / "d", "--preset", "tiny", *given).exit_code == 0
    assert (calls[0].policy.imagined_share, calls[0].round_warmup, calls[0].seed, calls[0].rounds) == (0, 0, 3, 2)


def test_a_runs_config_json_given_as_config_is_that_runs_settings_not_todays_defaults(tmp_path):
    # a run folder's config.json leaves out a field at its earlier default; read as a file of changes it took today's
    made_before = RunConfig(round_warmup=0.0, collect=CollectConfig(sigma_max=0.05, noise_rho=0.0))
    stored = made_before.to_dict()
    assert "round_warmup" not in stored and "noise_rho" not in stored["collect"]
    (tmp_path / "config.json").write_text(json.dumps({**stored, "provenance": {"version": "0.1.0"}}))
    assert load_config(tmp_path / "config.json", PRESETS["fastset"]) == made_before
    (tmp_path / "changes.json").write_text(json.dumps({"model": {"history": 3}}))  # a file of changes: on the base
    assert load_config(tmp_path / "changes.json", PRESETS["fastset"]).rounds == PRESETS["fastset"].rounds


def test_set_reaches_round(data, tmp_path, monkeypatch):
    save_model(ClosedLoopModel(MODEL_PRESETS["tiny"]), tmp_path / "m.pt")
    save_policy(AdjustmentPolicy(POLICY_PRESETS["tiny"]), tmp_path / "p.pt")
    monkeypatch.setattr(next_round, "next_round", capture())
    args = ("round", "--model", tmp_path / "m.pt", "--policy", tmp_path / "p.pt", "--data", data, "--out", tmp_path / "r")
    result = invoke(*args, "--preset", "tiny", "--set", "model.steps=40", "--set", "warm_budget=0.5", "--set", "seed=6")
    (_, _, _, _, model_schedule, policy_schedule, _, seed, *_), _ = captured(result)
    assert model_schedule.steps == 20 and policy_schedule.steps == POLICY_PRESETS["tiny"].steps // 2 and seed == 6


def test_set_reaches_run_and_demo(tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(pipeline, "demo", lambda out, cfg, console, max_plots: calls.append(cfg))
    result = invoke("demo", "--out", tmp_path / "d", "--preset", "tiny", "--set", "policy.k_smooth=0.25", "--rounds", "2")
    assert result.exit_code == 0, result.output
    assert calls == [dataclasses.replace(PRESETS["tiny"], policy=dataclasses.replace(PRESETS["tiny"].policy, k_smooth=0.25),
                                         rounds=2)]  # fmt: skip
    refused(invoke("demo", "--out", tmp_path / "e", "--set", "rounds=0"), "--set rounds=0: rounds must be an integer")


@pytest.mark.parametrize("command", ["study", "ablate"])
def test_set_reaches_study_and_ablate(command, tmp_path, monkeypatch):
    import efficienttrack.study as study
    from efficienttrack.data.references import save_references
    from toy_system import sine_refs

    name = "run_study" if command == "study" else "run_ablation"
    monkeypatch.setattr(study, name, capture())
    save_references(sine_refs([40, 40]), tmp_path / "refs")
    args = [command, *(["history"] if command == "ablate" else []), "--out", tmp_path / "s", "--preset", "tiny"]
    refs = ("--train-refs", tmp_path / "refs", "--test-refs", tmp_path / "refs", "--system", "toy_system:make")
    result = invoke(*args, *refs, "--set", "policy.k_smooth=0.25", "--seeds", "3")
    positional, _ = captured(result)
    study_arg, jobs = positional[:2] if command == "study" else positional[1:3]
    assert study_arg.run_config.policy.k_smooth == 0.25
    assert [(job.seed, job.run_config.seed, job.run_config.collect.seed) for job in jobs][:1] == [(3, 3, 3)]
    assert all(job.run_config.policy.k_smooth == 0.25 for job in jobs)


def test_the_earlier_preset_names_are_read_with_a_warning(tmp_path):
    from efficienttrack.baselines import method_settings
    from efficienttrack.core.settings import canonical_preset
    from efficienttrack.study import make_study
    from efficienttrack.systems.spec import SystemSpec
    from toy_system import sine_refs

    assert canonical_preset("cpu") == "cpu" and canonical_preset("paper") == "paper"
    with pytest.warns(FutureWarning, match="preset 'full' is now called 'cpu'"):
        assert canonical_preset("full") == "cpu"
    with pytest.warns(FutureWarning, match="preset 'quick' is now called 'tiny'"):
        assert method_settings("sac", "quick") == method_settings("sac", "tiny")
    refs = sine_refs([40, 40])
    with pytest.warns(FutureWarning):
        assert make_study(SystemSpec(), refs[:1], refs[1:], preset="quick").preset == "tiny"


def test_one_device_definition_admits_what_resolve_device_accepts():
    from efficienttrack.learn.nets import resolve_device

    assert RunConfig(device="cuda:1").device == "cuda:1"  # a second GPU is a device like the first
    for name in ("gpu", "cuda:", "cuda:x", "meta", "CPU"):
        with pytest.raises(EfficientTrackError, match="one of auto, cpu, cuda, cuda:N"):
            RunConfig(device=name)
        with pytest.raises(EfficientTrackError, match=f"--device '{name}': expected one of auto, cpu, cuda, cuda:N"):
            resolve_device(name)


@dataclasses.dataclass(frozen=True)
class Grown:
    """A settings class whose field ``share`` came later with a default (0.5) other than what the code did before (0)."""

    lr: float = setting(1e-3, gt=0)
    share: float = setting(0.5, ge=0, le=1, before=0.0)

    def __post_init__(self) -> None:
        check_fields(self)


def test_a_field_added_later_with_a_new_default_reads_old_stored_forms_as_they_were_made():
    assert plain_form(Grown()) == {"lr": 1e-3, "share": 0.5}  # the default differs from the past: kept, so compared
    assert plain_form(Grown(share=0.0)) == {"lr": 1e-3}  # the past's value: left out, as old folders stored it
    old = {"lr": 1e-3}  # written before the field existed
    assert settings_from_dict(Grown, old, "policy.json", stored=True).share == 0.0
    assert settings_from_dict(Grown, old, "a user's config").share == 0.5  # what a user leaves out takes the default
    assert settings_from_dict(Grown, {"lr": 1e-3, "share": 0.5}, "policy.json", stored=True).share == 0.5


def test_config_show_runs_without_torch():
    torch_free = (
        "import sys; sys.modules['torch'] = None\n"  # an import of torch fails as on the core install
        "sys.argv = ['efficienttrack', 'config', 'show', 'tiny', '--set', 'policy.lr=0.01']\n"
        "from efficienttrack import cli\n"
        "cli.main()\n"
    )
    done = subprocess.run([sys.executable, "-c", torch_free], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert "# efficienttrack settings: preset tiny, --set policy.lr=0.01" in done.stdout and "  lr: 0.01 " in done.stdout


@pytest.mark.parametrize("method", ["supertrack", "efficienttrack"])
@pytest.mark.parametrize("preset_name", ["tiny", "cpu"])
def test_the_baselines_and_the_open_loop_keep_the_loss_they_were_measured_with(method, preset_name):
    assert (PolicyConfig().imagined_share, PolicyConfig().row_cap) == (0.5, 10.0)  # the closed loop's defaults
    policy = preset_settings(method, preset_name).policy  # SuperTrack's loss; the open loop's
    assert (policy.imagined_share, policy.row_cap) == (0.0, 0.0)


def test_settings_that_train_before_they_could_fail_refuse_a_device_this_machine_lacks():
    import torch

    from efficienttrack.baselines.openloop import OpenLoopSettings

    if torch.cuda.is_available():
        pytest.skip("CUDA is available here: 'cuda' is a device this machine has")
    for cls in (SuperTrackSettings, OpenLoopSettings):
        with pytest.raises(EfficientTrackError, match=f"^{cls.__name__}.device must be auto or cpu \\(CUDA is not avail"):
            cls(device="cuda")

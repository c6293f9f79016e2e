import json
import shutil
from dataclasses import replace

import numpy as np
import pytest

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.data.references import Reference, save_references
from efficienttrack.deploy.episodes import Guard
from efficienttrack.systems.protocol import BatchedSystem
from efficienttrack.systems.spec import load_system
from efficienttrack.workflow.collect import CollectConfig, autoregress, collect, episode_noise
from toy_system import make, sine_refs


@pytest.fixture
def refs():
    return sine_refs([60, 45, 80])


def test_noise_clipped_sigma_bounded_and_clean_passes_exact(refs):
    cfg = CollectConfig(sigma_max=0.05, noise_ratio=(3, 1), passes=4, seed=3)
    result = collect(BatchedSystem(make()), refs, cfg, progress=False)
    assert len(result.records) == 12
    for record in result.records:
        d = record.q_ref - record.q_des
        sigma = record.meta["sigma"]
        if record.meta["noisy"]:
            assert 0 < sigma <= 0.05
            assert np.all(np.abs(d) <= sigma + 1e-12)
            assert np.abs(d).max() == pytest.approx(sigma)  # some steps hit the clip
        else:
            assert sigma == 0.0
            assert np.all(d == 0.0)
    assert sum(r.meta["noisy"] for r in result.records) == 9  # 3:1 over 12 episodes


def test_a_noise_level_beyond_the_adjustment_bound_is_refused_before_anything_moves():
    system = load_system("xe75")
    with pytest.raises(EfficientTrackError, match=r"sigma_max: 1 rad exceeds .* 0\.15 rad \(boom.*--set collect\.sigma_max="):
        collect(system, sine_refs([20]), CollectConfig(sigma_max=1.0), progress=False)


def test_noisy_references_stay_within_the_joint_limits_and_the_clamps_are_counted():
    system = load_system("xe75")
    system.limits = system.limits.replace(max_adjust=(1.0, 1.0, 1.0, 1.0), max_adjust_rate=(0.5, 0.5, 0.5, 0.5))
    limits = system.limits
    near_stop = np.tile(np.array(limits.q_max) - 0.02, (40, 1))  # 2 cm of angle below every upper stop
    near_stop[:, 3] = 0.0
    cfg = CollectConfig(sigma_max=1.0, noise_ratio=(1, 0), passes=1, seed=2)
    record = collect(system, [Reference("near_stop", near_stop)], cfg, progress=False).records[0]
    assert not limits.outside(record.q_ref).any()
    clamped = record.meta["guard"][Guard.CLAMPED.name.lower()]
    assert len(clamped) > 10
    d = record.q_ref - record.q_des
    assert np.all(d[:, :3] <= 0.02 + 1e-12) and d[:, :3].max() == pytest.approx(0.02)  # clamped at the stops


def test_noise_distribution_is_clipped_gaussian():
    cfg = CollectConfig(sigma_max=0.05, noise_rho=0.0, seed=1)
    sigma, d = episode_noise(cfg, pass_index=2, ref_index=5, steps=20000)
    assert 0 < sigma <= 0.05
    assert np.all(np.abs(d) <= sigma)
    # N(0, 1) clipped to ±1: std 0.7184 and 31.7 % of samples on the bounds
    assert np.std(d) / sigma == pytest.approx(0.7184, abs=0.01)
    assert np.mean(np.abs(d) == sigma) == pytest.approx(0.3173, abs=0.01)
    sigmas = [episode_noise(cfg, 0, i, 1)[0] for i in range(2000)]
    assert max(sigmas) <= 0.05 and np.mean(sigmas) == pytest.approx(0.025, abs=0.001)


def test_correlated_noise_keeps_the_level_and_the_clip_and_rho_0_is_the_white_noise_unchanged():
    white = CollectConfig(sigma_max=0.05, noise_rho=0.0, seed=1)
    sigma, d = episode_noise(white, pass_index=2, ref_index=5, steps=20000)
    rng = np.random.default_rng([1, 2, 5])  # the paper's formula, drawn as before the option existed
    assert sigma == rng.uniform(0.0, 0.05)
    assert np.array_equal(d, np.clip(rng.normal(0.0, sigma, size=(20000, 4)), -sigma, sigma))
    slow_sigma, slow = episode_noise(replace(white, noise_rho=0.9), pass_index=2, ref_index=5, steps=20000)
    assert slow_sigma == sigma and np.all(np.abs(slow) <= sigma)
    assert np.std(slow) / sigma == pytest.approx(0.7184, abs=0.03)  # the same clipped level: stationary from step 0
    lag1 = np.mean([np.corrcoef(slow[1:, j], slow[:-1, j])[0, 1] for j in range(4)])
    assert 0.85 < lag1 < 0.9  # ρ = 0.9 before the clip, a little less after it
    assert abs(np.corrcoef(d[1:, 0], d[:-1, 0])[0, 1]) < 0.03


def test_the_noise_filter_is_scipys_ar1_in_numpy_alone():
    from scipy.signal import lfilter

    e = np.random.default_rng(0).normal(size=(600, 4))  # blocks of 256: two whole and a part
    for rho in (0.0, 0.5, 0.9, 0.99):
        assert np.allclose(autoregress(e, rho), lfilter([1.0], [1.0, -rho], e, axis=0), rtol=1e-12, atol=1e-12)


def test_a_collection_folder_from_before_noise_rho_resumes_and_a_correlated_one_is_told_apart(tmp_path, refs):
    cfg = CollectConfig(noise_rho=0.0, passes=2, seed=4)
    first = collect(BatchedSystem(make()), refs, cfg, out=tmp_path, progress=False)
    manifest = json.loads((tmp_path / "collect.json").read_text())
    assert "noise_rho" not in manifest["config"]  # the form of the folders made before the field existed
    again = collect(BatchedSystem(make()), refs, cfg, out=tmp_path, progress=False)
    assert again.resumed_passes == 2 and again.interaction_steps == first.interaction_steps
    with pytest.raises(EfficientTrackError, match=r"collect\.json: this folder holds a collection with other settings"):
        collect(BatchedSystem(make()), refs, replace(cfg, noise_rho=0.5), out=tmp_path, progress=False)
    assert CollectConfig(noise_rho=0.5).to_dict()["noise_rho"] == 0.5
    # a run's settings likewise: a run folder from before the field reads back as white noise, today's as correlated
    from efficienttrack.workflow.config import PRESETS, RunConfig, amend, from_dict

    before = RunConfig().to_dict()
    del before["collect"]["noise_rho"]
    assert from_dict(before, "config.json", stored=True).collect.noise_rho == 0.0
    assert RunConfig().collect.noise_rho == 0.9 and from_dict(RunConfig().to_dict(), stored=True) == RunConfig()
    white = amend(RunConfig(), {"collect": {"noise_rho": 0}}, "--set")
    assert white.collect.noise_rho == 0.0 and amend(white, {"seed": 3}, "--seed").collect.noise_rho == 0.0
    # the paper preset keeps the paper's noise: σ_max 0.05, white
    assert (PRESETS["paper"].collect.sigma_max, PRESETS["paper"].collect.noise_rho) == (0.05, 0.0)


@pytest.mark.parametrize("rho", [-0.1, 1.0, float("nan")])
def test_a_noise_correlation_outside_0_to_0_99_is_refused_naming_the_field(rho):
    with pytest.raises(EfficientTrackError, match="noise_rho"):
        CollectConfig(noise_rho=rho)


@pytest.mark.parametrize(
    ("ratio", "passes", "references", "noisy"),
    [
        ((9, 2), 1, 40, 33),
        ((9, 2), 11, 40, 360),
        ((9, 2), 10, 32, 262),
        ((1, 1), 4, 3, 6),
        ((1, 0), 3, 5, 15),
        ((0, 1), 3, 5, 0),
    ],
)
def test_episode_ratio_kept_by_every_number_of_passes(ratio, passes, references, noisy):
    cfg = CollectConfig(noise_ratio=ratio, passes=passes, seed=4)
    masks = np.array([cfg.noisy_episodes(k, references) for k in range(passes)])
    assert masks.shape == (passes, references) and masks.sum() == noisy
    share = ratio[0] / sum(ratio)
    assert np.all(np.abs(np.cumsum(masks.sum(axis=1)) - np.arange(1, passes + 1) * references * share) <= 0.5 + 1e-9)
    if 0 < noisy < passes * references and passes > 1:  # the noisy references differ from pass to pass
        assert len({tuple(m) for m in masks}) > 1


def test_interaction_steps_time_and_commands(refs):
    result = collect(BatchedSystem(make()), refs, CollectConfig(passes=3), progress=False)
    assert result.interaction_steps == 3 * (59 + 44 + 79)
    record = result.records[1]
    assert len(record) == 44 and np.allclose(record.t, np.arange(44) * 0.05)
    np.testing.assert_array_equal(record.q_des, refs[1].q[1:])
    # toy system: u = 1000·k·(q_ref − q), and q[t+1] = q[t] + k·(q_ref[t] − q[t])
    np.testing.assert_allclose(record.u, 400 * (record.q_ref - record.q), atol=1e-12)
    np.testing.assert_allclose(record.q[1:], record.q[:-1] + 0.4 * (record.q_ref[:-1] - record.q[:-1]), atol=1e-12)


def test_batched_equals_one_at_a_time_for_different_lengths(refs):
    cfg = CollectConfig(noise_ratio=(2, 1), passes=3, seed=7)
    batched = collect(BatchedSystem(make(batched=True)), refs, cfg, progress=False)
    single = collect(BatchedSystem(make(batched=False)), refs, cfg, progress=False)
    assert [len(r) for r in batched.records] == [len(r) for r in single.records]
    for a, b in zip(batched.records, single.records, strict=True):
        for name in ("q", "qd", "q_ref", "q_des", "u", "t"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
        assert a.meta == b.meta


def test_batched_equals_one_at_a_time_on_xe75(refs):
    cfg = CollectConfig(noise_ratio=(0, 1), passes=1)
    batched = collect(load_system("xe75"), refs, cfg, progress=False).records
    for ref, a in zip(refs, batched, strict=True):
        b = collect(load_system("xe75"), [ref], cfg, progress=False).records[0]
        np.testing.assert_allclose(a.q, b.q, rtol=0, atol=1e-12)
        np.testing.assert_allclose(a.u, b.u, rtol=0, atol=1e-9)


def test_resume_after_interruption(tmp_path, refs):
    cfg = CollectConfig(noise_ratio=(1, 1), passes=4, seed=5)
    first = collect(BatchedSystem(make()), refs, cfg, out=tmp_path, progress=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["collect.json", "pass_000", "pass_001", "pass_002", "pass_003"]
    shutil.rmtree(tmp_path / "pass_002")
    shutil.rmtree(tmp_path / "pass_003")
    again = collect(BatchedSystem(make()), refs, cfg, out=tmp_path, progress=False)
    assert again.resumed_passes == 2 and again.interaction_steps == first.interaction_steps
    for a, b in zip(first.records, again.records, strict=True):
        np.testing.assert_array_equal(a.q_ref, b.q_ref)
        assert a.meta["name"] == b.meta["name"] and a.meta["pass"] == b.meta["pass"]
    with pytest.raises(EfficientTrackError, match="other settings"):
        collect(BatchedSystem(make()), refs, CollectConfig(passes=5), out=tmp_path, progress=False)


class CrashAfter:
    """An unbatched machine that fails after ``resets`` episodes, like a real machine's link dropping mid-pass."""

    def __init__(self, resets: int) -> None:
        self.inner, self.resets = make(batched=False), resets
        self.dt = self.inner.dt

    def reset(self, q0):
        if self.resets == 0:
            raise ConnectionError("link lost")
        self.resets -= 1
        return self.inner.reset(q0)

    def step(self, q_ref):
        return self.inner.step(q_ref)


def test_unbatched_machine_flushes_every_episode_and_resumes_mid_pass(tmp_path, refs):
    cfg = CollectConfig(noise_ratio=(1, 0), passes=1, seed=2)
    with pytest.raises(EfficientTrackError, match=r"collect: pass 1 failed on episode\(s\) ref_02: ConnectionError"):
        collect(BatchedSystem(CrashAfter(resets=2)), refs, cfg, out=tmp_path, progress=False)
    partial = tmp_path / ".pass_000.partial"
    assert sorted(p.stem for p in partial.glob("*.npz")) == ["ref_00", "ref_01"]
    machine = CrashAfter(resets=1)  # only the third episode is left to run
    resumed = collect(BatchedSystem(machine), refs, cfg, out=tmp_path, progress=False)
    assert machine.resets == 0 and not partial.exists() and (tmp_path / "pass_000").is_dir()
    whole = collect(BatchedSystem(make(batched=False)), refs, cfg, progress=False)
    for a, b in zip(resumed.records, whole.records, strict=True):
        np.testing.assert_array_equal(a.q_ref, b.q_ref)
        assert a.meta == b.meta


def test_too_few_passes_for_any_noise_warn(refs):
    with pytest.warns(UserWarning, match="give no noisy episode"):
        collect(BatchedSystem(make()), refs[:1], CollectConfig(passes=1, noise_ratio=(1, 3)), progress=False)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"sigma_max": -0.1}, "sigma_max"),
        ({"noise_ratio": (0, 0)}, "noise_ratio"),
        ({"noise_ratio": (float("nan"), 2)}, "noise_ratio"),
        ({"passes": 0}, "passes"),
    ],
)
def test_bad_config(kwargs, message):
    with pytest.raises(EfficientTrackError, match=message):
        CollectConfig(**kwargs)


@pytest.mark.parametrize("ratio", [(9.0, 2.0), (0.1, 3.0), (1e-7, 2.5), (0.0, 1.0)])
def test_noise_ratio_text_reads_back_exactly(ratio):
    text = CollectConfig(noise_ratio=ratio).noise_ratio_text
    assert CollectConfig.parse_noise_ratio(text) == ratio
    assert CollectConfig().noise_ratio_text == "9:2"


@pytest.mark.parametrize("text", ["9", "9:2:1", "a:2", "9-2", ""])
def test_noise_ratio_text_errors_name_the_option(text):
    with pytest.raises(EfficientTrackError, match=f"--noise-ratio '{text}': expected noisy:clean"):
        CollectConfig.parse_noise_ratio(text)


def test_cli_collect_defaults_are_the_config_defaults(tmp_path):
    from typer.testing import CliRunner

    from efficienttrack.cli import app

    save_references(sine_refs([12, 9]), tmp_path / "refs")
    args = ["collect", "--system", "toy_system:make", "--refs", str(tmp_path / "refs"), "--out", str(tmp_path / "col")]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    written = json.loads((tmp_path / "col" / "collect.json").read_text())["config"]
    assert written == CollectConfig().to_dict()
    result = CliRunner().invoke(app, [*args, "--noise-ratio", "9/2"])
    assert isinstance(result.exception, EfficientTrackError) and "--noise-ratio '9/2'" in str(result.exception)


def test_a_system_that_cannot_be_built_is_one_error_naming_it():
    with pytest.raises(EfficientTrackError, match="hydraulic simulator: option 'seed': a seed must be an integer"):
        load_system("xe75", seed=-1)
    with pytest.raises(EfficientTrackError, match=r"system 'test_collect:broken_machine': building it failed: RuntimeError"):
        load_system("test_collect:broken_machine")


def broken_machine():
    raise RuntimeError("adapter cannot open /dev/can0")

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from efficienttrack.cli import app
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.data.records import EpisodeRecord, save_csv
from efficienttrack.systems import load_plant, load_system
from efficienttrack.systems.fit import (
    FitConfig,
    Padded,
    Steady,
    calibrate,
    closed_loop_rollout,
    estimate_sensor_noise,
    fidelity,
    load_logs,
    logged_accel,
    make_windows,
    open_loop_replay,
    pad,
    reference_jitter,
    rollout_windows,
    save_params,
    simulate_episodes,
    steady_samples,
    tracking_mae,
    travel_ratio,
    window_error,
)
from efficienttrack.systems.fit.calibrate import _bin_weights, _linkage_guess
from efficienttrack.systems.hydraulic import HydraulicExcavator, HydraulicParams, requested_velocity
from efficienttrack.systems.pd import XE75_PD, ClosedLoop
from efficienttrack.systems.protocol import BatchedSystem

DATA = Path(__file__).parents[2] / "shared" / "data" / "xe75"

TRUE = HydraulicParams(
    delay=(3, 4, 4, 3),
    tau=(0.12, 0.06, 0.04, 0.2),
    dead_zone_pos=(450.0, 380.0, 500.0, 420.0),
    dead_zone_neg=(600.0, 400.0, 450.0, 470.0),
    pwm_sat_pos=(950.0, 720.0, 950.0, 680.0),
    pwm_sat_neg=(900.0, 800.0, 700.0, 950.0),
    v_max_pos=(0.2, 0.4, 1.2, 0.4),
    v_max_neg=(0.3, 0.3, 1.0, 0.45),
    pump_coupling=((0.0,) * 4,) * 4,
    q_min=(-0.6, -1.2, -0.6, -np.pi),
    q_max=(0.7, 0.6, 2.4, np.pi),
)


def synthetic_records(params, episodes=6, steps=240, seed=0):
    """PD runs of the simulator on smooth random references with noisy q_ref (like pd_noise_train)."""
    rng = np.random.default_rng(seed)
    t = np.arange(steps + 1) * 0.05
    freq = rng.uniform(0.05, 0.2, (episodes, 4))
    amp = rng.uniform(0.1, 0.4, (episodes, 4)) * np.array([0.5, 1.0, 1.5, 1.5])
    ref = amp[None] * np.sin(2 * np.pi * freq[None] * t[:, None, None] + rng.uniform(0, 6, (episodes, 4)))
    q_des = ref[1:]
    q_ref = q_des + 0.02 * np.clip(rng.standard_normal(q_des.shape), -1, 1)
    system = ClosedLoop(HydraulicExcavator(params), XE75_PD)
    q = np.empty_like(q_des)
    qd = np.empty_like(q_des)
    u = np.empty_like(q_des)
    obs = system.reset(ref[0])
    for k in range(steps):
        q[k], qd[k] = obs[:, :4], obs[:, 4:]
        obs = system.step(q_ref[k])
        u[k] = system.last_command
    return [
        EpisodeRecord(q=q[:, i], qd=qd[:, i], q_ref=q_ref[:, i], q_des=q_des[:, i], u=u[:, i], t=t[:steps]).validate()
        for i in range(episodes)
    ]


@pytest.mark.slow
def test_calibrate_recovers_a_known_simulator():
    records = synthetic_records(TRUE, episodes=12, steps=100)  # short episodes: the last stage simulates them whole
    start = TRUE.replace(
        delay=(4, 4, 4, 4),
        tau=(0.1, 0.1, 0.1, 0.1),
        dead_zone_pos=(500.0,) * 4,
        dead_zone_neg=(500.0,) * 4,
        v_max_pos=(0.3, 0.3, 0.8, 0.3),
        v_max_neg=(0.3, 0.3, 0.8, 0.3),
    )
    config = FitConfig(
        delays=(3, 4), open_horizon=10, closed_horizon=20, max_windows=60, max_episodes=4, max_nfev=10, max_ref_jitter=0.05
    )
    windows = make_windows(pad(records), 10, stride=20)
    before = window_error(rollout_windows(start, windows), windows)
    result = calibrate(records, start, config)
    fit = result.params
    assert fit.delay == TRUE.delay
    assert max(fit.tau_spool) < 0.05  # little spool lag where there is none (it trades off against the actuator lag)
    assert np.all(result.open_loop_deg < 0.35) and np.all(result.closed_loop_deg < 0.6)
    assert result.open_loop_deg.mean() < 0.4 * np.degrees(before).mean()
    np.testing.assert_allclose(result.mae_ratio, 1.0, atol=0.2)


def test_steady_samples_keep_held_commands_with_a_settled_speed():
    steps = 30
    u = np.zeros((steps, 1, 4))
    u[:, 0, 0] = 600.0  # held all along
    u[::2, 0, 1] = 600.0  # chatters
    u[:, 0, 2] = np.where(np.arange(steps) < 15, 0.0, 600.0)  # held at 0, then at 600 from step 15
    qd = np.zeros((steps, 1, 4))
    qd[:, 0, 3] = 0.045 * np.arange(steps)  # accelerating: settled only once the change is small against the speed
    z = np.zeros((steps, 1, 4))
    data = Padded(q=z, qd=qd, u=u, q_ref=z, q_des=z, lengths=np.array([steps]))
    steady = steady_samples(data, delay=[2, 2, 2, 2], hold=5, min_count=1)
    rows = np.arange(7, steps - 1)  # the steps t with a full held window t − 2 − 4 … t − 2
    np.testing.assert_array_equal(steady.mask[:, 0], True)
    np.testing.assert_array_equal(steady.mask[:, 1], False)
    np.testing.assert_array_equal(steady.mask[:, 2], (rows - 2 < 15) | (rows - 2 - 4 >= 15))  # not across the switch
    np.testing.assert_array_equal(steady.mask[:, 3], rows >= 16)  # 0.09 rad/s ≤ 0.1·0.045·t + 0.02 from t = 15.6
    np.testing.assert_array_equal(steady.u[:, 0], 600.0)
    few = steady_samples(data, delay=[2, 2, 2, 2], hold=5, min_count=len(rows))
    np.testing.assert_array_equal(few.mask.any(axis=0), [True, False, False, False])  # only joint 0 is settled throughout


def test_steady_samples_count_commands_beyond_saturation_as_held():
    steps = 30
    u = np.zeros((steps, 1, 4))
    u[:, 0, 0] = np.where(np.arange(steps) % 2, 900.0, 1000.0)  # a PD law at full speed wavering beyond saturation
    u[:, 0, 1] = np.where(np.arange(steps) % 2, -700.0, -1000.0)  # wavering across the saturation
    z = np.zeros((steps, 1, 4))
    data = Padded(q=z, qd=z, u=u, q_ref=z, q_des=z, lengths=np.array([steps]))
    plain = steady_samples(data, delay=[2, 2, 2, 2], hold=5, min_count=1)
    assert not plain.mask[:, :2].any()
    clipped = steady_samples(data, delay=[2, 2, 2, 2], hold=5, min_count=1, saturation=([850.0] * 4, [850.0] * 4))
    assert clipped.mask[:, 0].all() and not clipped.mask[:, 1].any()
    np.testing.assert_array_equal(np.abs(clipped.u[:, 0]) >= 900.0, True)  # the logged command, not the clipped one


def test_bin_weights_give_each_band_of_the_held_command_equal_weight():
    u = np.zeros((1000, 4))
    u[:900, 0], u[900:, 0] = 450.0, 950.0  # 900 steps near the dead zone, 100 at full PWM
    u[:, 1] = np.where(np.arange(1000) < 500, 600.0, -600.0)  # one band per direction
    u[:990, 2], u[990:, 2] = 450.0, 950.0  # a rare band below the floor of 30 steps
    mask = np.ones((1000, 4), bool)
    mask[:, 3] = False
    w = _bin_weights(Steady(u=u, q=u, qd=u, qd_next=u, mask=mask), floor=30)
    band_weight = [(w[:900, 0] ** 2).sum(), (w[900:, 0] ** 2).sum()]
    np.testing.assert_allclose(band_weight, [0.5, 0.5])
    np.testing.assert_allclose([(w[:500, 1] ** 2).sum(), (w[500:, 1] ** 2).sum()], [0.5, 0.5])
    np.testing.assert_allclose((w[990:, 2] ** 2).sum(), 0.5 * 10 / 30)  # 10 steps weigh as a third of a band
    np.testing.assert_array_equal(w[:, 3], 0.0)


def test_linkage_guess_recovers_a_known_linkage():
    linked = TRUE.replace(speed_q=(0.3, -0.2, 0.6, 0.0), speed_q2=(0.0, 0.1, -0.3, 0.0))
    rng = np.random.default_rng(0)
    n = 4000
    q = rng.uniform(TRUE.q_min, TRUE.q_max, (n, 4))
    u = rng.choice([-1.0, 1.0], (n, 4)) * rng.uniform(650.0, 1000.0, (n, 4))
    qd = requested_velocity(u, q, np.zeros((n, 4)), linked)
    guess = _linkage_guess(TRUE, Steady(u=u, q=q, qd=qd, qd_next=qd, mask=np.ones((n, 4), bool)))
    np.testing.assert_allclose(guess.speed_q, linked.speed_q, atol=1e-6)
    np.testing.assert_allclose(guess.speed_q2, linked.speed_q2, atol=1e-6)
    np.testing.assert_allclose(guess.v_max_pos, TRUE.v_max_pos, rtol=1e-6)


def test_logged_accel_is_a_high_quantile_of_the_logged_acceleration():
    steps = 200
    qd = np.zeros((steps, 1, 4))
    qd[:, 0] = np.arange(steps)[:, None] * 0.05 * np.array([1.0, 2.0, 0.5, 0.0])  # constant accelerations, rad/s²
    z = np.zeros((steps, 1, 4))
    data = Padded(q=z, qd=qd, u=z, q_ref=z, q_des=z, lengths=np.array([steps]))
    np.testing.assert_allclose(logged_accel(data), [1.0, 2.0, 0.5, 0.0], atol=1e-9)


def test_calibration_leaves_out_strongly_perturbed_episodes():
    noisy = synthetic_records(TRUE, episodes=2, steps=60, seed=5)  # q_ref jitters by about 0.02 rad
    assert all(0.01 < reference_jitter(r) < 0.05 for r in noisy)
    calm = EpisodeRecord(**{**noisy[0].__dict__, "q_ref": noisy[0].q_des.copy()})
    assert reference_jitter(calm) == 0.0
    lines = []
    config = FitConfig(delays=(4,), open_horizon=5, closed_horizon=10, max_windows=10, max_nfev=1)
    calibrate([calm, *noisy], TRUE, config, progress=lines.append)
    assert lines[0].startswith("fitting on 1 of 3 episodes")
    with pytest.raises(EfficientTrackError, match="max_ref_jitter"):
        calibrate(noisy, TRUE, config)


def test_fidelity_of_the_true_simulator_is_perfect():
    records = synthetic_records(TRUE, episodes=3, steps=120, seed=1)
    records[1] = EpisodeRecord(
        **{**records[1].__dict__, **{k: getattr(records[1], k)[:90] for k in ("q", "qd", "q_ref", "q_des", "u", "t")}}
    )
    system = BatchedSystem(ClosedLoop(HydraulicExcavator(TRUE), XE75_PD))
    plant = BatchedSystem(HydraulicExcavator(TRUE))
    result = fidelity(records, system, plant)
    np.testing.assert_allclose(result.ratio, 1.0, atol=1e-9)
    np.testing.assert_allclose(result.mpe20_deg, 0.0, atol=1e-9)
    np.testing.assert_allclose(result.travel_ratio20, 1.0, atol=1e-9)
    # padded episodes are masked: the short one's MAE equals its own unpadded MAE
    alone = tracking_mae(records[1].q[:, None], pad([records[1]]))[0]
    np.testing.assert_allclose(tracking_mae(result.q_sim, result.data)[1], alone, atol=1e-12)
    line = json.dumps(result.to_json())
    assert set(json.loads(line)) == {"closed_loop", "open_loop"}


def test_travel_ratio_tells_a_too_slow_simulator_from_a_too_fast_one():
    records = synthetic_records(TRUE, episodes=3, steps=160, seed=5)
    system = BatchedSystem(ClosedLoop(HydraulicExcavator(TRUE), XE75_PD))

    def travel(speed: float) -> np.ndarray:
        scaled = TRUE.replace(v_max_pos=[v * speed for v in TRUE.v_max_pos], v_max_neg=[v * speed for v in TRUE.v_max_neg])
        return fidelity(records, system, BatchedSystem(HydraulicExcavator(scaled))).travel_ratio20

    slow, fast = travel(0.8), travel(1.25)
    assert np.all((slow > 1.1) & (slow < 1.4)), slow  # the real machine goes further than a too-slow simulator
    assert np.all((fast > 0.7) & (fast < 0.9)), fast
    windows = make_windows(pad(records), 20, stride=10)
    still = travel_ratio(np.broadcast_to(windows.q0, windows.q.shape), windows)
    assert np.isnan(still).all()  # a simulator that never moves has no ratio, and the report says null
    report = fidelity(records, system, BatchedSystem(HydraulicExcavator(TRUE)))._replace(travel_ratio20=still).to_json()
    assert report["open_loop"]["travel_ratio20"] == [None] * 4
    json.dumps(report, allow_nan=False)


def test_fast_episode_simulation_equals_the_closed_loop_system():
    # both start at rest at the logged start and take the first step with e_prev = e (PDGains.step with None)
    records = synthetic_records(TRUE, episodes=3, steps=80, seed=4)
    data = pad(records)
    params = TRUE.replace(
        pump_coupling=((0.1, 0.2, 0.3, 0.4),) * 4, tau_spool=(0.02, 0.05, 0.0, 0.1), dead_zone_rest=(50.0, 40.0, 30.0, 20.0)
    )
    fast = simulate_episodes(params, data, XE75_PD)
    reference = closed_loop_rollout(BatchedSystem(ClosedLoop(HydraulicExcavator(params), XE75_PD)), data)
    np.testing.assert_allclose(fast, reference, rtol=0, atol=1e-12)


def test_open_loop_error_of_a_plant_without_history_starts_at_rest():
    class AtRest:
        """The same simulator seen through the bare Plant protocol (no qd0/u_past on reset)."""

        batched = True
        dt = 0.05

        def __init__(self):
            self.inner = HydraulicExcavator(TRUE)

        def reset(self, q0):
            return self.inner.reset(q0)

        def step(self, u):
            return self.inner.step(u)

    records = synthetic_records(TRUE, episodes=2, steps=100, seed=2)
    data = pad(records)
    w = make_windows(data, 20, stride=10)
    plant = HydraulicExcavator(TRUE)
    plant.reset(w.q0)
    q = np.stack([plant.step(u)[:, :4] for u in w.u])
    expected = np.abs(q - w.q).mean(axis=(0, 1))
    np.testing.assert_allclose(window_error(*open_loop_replay(BatchedSystem(AtRest()), data)), expected, atol=1e-12)
    assert np.all(expected > 0)


def test_cli_fidelity_and_calibrate(tmp_path):
    logs = tmp_path / "logs"
    # 70 steps: room for the calibration's 60-step closed-loop windows (the fit's cost grows with the steps)
    for i, record in enumerate(synthetic_records(TRUE, episodes=2, steps=70, seed=3)):
        record.save(logs / f"ep{i}.npz")
    preset = save_params(TRUE, tmp_path / "true.json")
    runner = CliRunner()
    out = runner.invoke(
        app,
        [
            "sim",
            "fidelity",
            "--logs",
            str(logs),
            "--system-opt",
            f"params_file={preset}",
            "--json",
            "--plot",
            str(tmp_path / "plots"),
            "--episodes",
            "1",
        ],
    )
    assert out.exit_code == 0, out.output
    report = json.loads(out.output.strip().splitlines()[-1])
    np.testing.assert_allclose(report["closed_loop"]["ratio"], 1.0, atol=1e-3)
    assert len(list((tmp_path / "plots").glob("*.png"))) == 1
    calm = synthetic_records(TRUE, episodes=1, steps=70, seed=3)[0]
    calm = EpisodeRecord(**{**calm.__dict__, "q_ref": calm.q_des.copy()})  # jitter 0; the others jitter ~0.02 rad
    calm.save(logs / "calm.npz")
    fid = ["sim", "fidelity", "--logs", str(logs), "--system-opt", f"params_file={preset}"]
    out = runner.invoke(app, [*fid, "--max-ref-jitter", "0.01"])
    assert out.exit_code == 0 and out.output.startswith("1 episodes"), out.output
    out = runner.invoke(app, [*fid, "--min-ref-jitter", "0.01"])
    assert out.exit_code == 0 and out.output.startswith("2 episodes"), out.output
    out = runner.invoke(app, [*fid, "--min-ref-jitter", "0.05"])
    assert out.exit_code != 0 and "--min-ref-jitter/--max-ref-jitter: no episode" in str(out.exception), out.output
    (logs / "calm.npz").unlink()
    out = runner.invoke(
        app,
        [
            "sim",
            "calibrate",
            "--logs",
            str(logs),
            "--out",
            str(tmp_path / "fit.json"),
            "--start",
            str(preset),
            "--delays",
            "3,4",
            "--max-windows",
            "40",
            "--max-nfev",
            "2",
            "--max-ref-jitter",
            "0.05",
        ],
    )
    assert out.exit_code == 0, out.output
    assert HydraulicParams.load(tmp_path / "fit.json").delay[1] == 4


@pytest.mark.skipif(not DATA.is_dir(), reason="real XE75 logs not found at ../shared/data/xe75")
def test_shipped_preset_closed_loop_ratio_on_pd_clean_train():
    records = load_logs([DATA / "pd_clean_train"])
    result = fidelity(records, load_system("xe75"), load_plant("xe75"), stride=40)
    np.testing.assert_allclose(result.real_mae_deg, [1.45, 4.72, 5.05, 10.54], atol=0.01)  # the README's figures
    assert np.all((result.ratio > 0.85) & (result.ratio < 1.15)), result.ratio


def test_sensor_noise_estimate_recovers_white_noise_levels():
    rng = np.random.default_rng(5)
    t = np.arange(400) * 0.05
    smooth = 0.3 * np.sin(0.5 * t)[:, None] * np.ones(4)
    q = smooth + rng.standard_normal((400, 4)) * np.array([1e-3, 2e-3, 1e-3, 5e-4])
    qd = np.zeros_like(q)
    qd[1:] = (q[1:] - q[:-1]) / 0.05 + rng.standard_normal((399, 4)) * 0.02
    record = EpisodeRecord(q=q, qd=qd, q_ref=q, q_des=q, u=np.zeros_like(q), t=t).validate()
    noise_q, noise_qd = estimate_sensor_noise(pad([record]))
    np.testing.assert_allclose(noise_q, [1e-3, 2e-3, 1e-3, 5e-4], rtol=0.15)
    np.testing.assert_allclose(noise_qd, 0.02, rtol=0.15)


def test_fit_config_is_validated():
    with pytest.raises(EfficientTrackError, match="delays"):
        FitConfig(delays=())
    with pytest.raises(EfficientTrackError, match="max_nfev"):
        FitConfig(max_nfev=0)
    out = CliRunner().invoke(app, ["sim", "calibrate", "--logs", "/nonexistent", "--out", "x.json", "--delays", "a,b"])
    assert out.exit_code != 0


def test_load_logs_reads_any_record_format_and_names_an_episode_without_pwm(tmp_path):
    records = synthetic_records(TRUE, episodes=2, steps=20, seed=6)
    records[0].save(tmp_path / "a" / "ep0.npz")
    save_csv(records[1], tmp_path / "a" / "sub" / "ep1.csv")  # the records loader: every format, subfolders on request
    loaded = load_logs([tmp_path / "a"], recursive=True)
    np.testing.assert_array_equal(pad(loaded).u, pad(records).u)
    EpisodeRecord(**{**records[0].__dict__, "u": None}).save(tmp_path / "b" / "no_pwm.npz")
    with pytest.raises(EfficientTrackError, match="no_pwm has no PWM command 'u'"):
        load_logs([tmp_path / "b"])
    assert load_logs([tmp_path / "b"], need_u=False)[0].u is None

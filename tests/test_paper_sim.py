"""The paper's simulator (``--system paper``): its published steps, batching, the PD preset, and Table I's PD row."""

from __future__ import annotations

from pathlib import Path

import gymnasium
import numpy as np
import pytest

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.data.cycles import generate_references
from efficienttrack.data.metrics import compute_metrics
from efficienttrack.data.references import Reference, load_references
from efficienttrack.deploy.runtime import track
from efficienttrack.envs import CLOSED_LOOP_ID, OPEN_LOOP_ID
from efficienttrack.systems.paper import Q_MAX, Q_MIN, PaperExcavator, swing_velocity
from efficienttrack.systems.pd import PAPER_PD
from efficienttrack.systems.spec import SystemSpec

TEST_REFS = Path(__file__).resolve().parents[2] / "shared" / "data" / "references" / "test"

# Steps recorded by the research repository's simulator (simulation/data_with_noise_test, printed to 8 digits):
# position q (4,), PWM u (4,) → the velocity of that step and the next position.
LOGGED_STEPS = np.array(
    [
        # boom lowering, arm raising, swing inside its positive law
        [0.30868134, -0.33983066, 0.43085437, -0.82868211, -44.05684795, 38.5504505, -20.07252486, 59.3888255,
         0.03774344, -0.01127372, 0.00119586, 0.25737367, 0.31056851, -0.34039435, 0.43091416, -0.81581343],
        [0.30936487, -0.13244078, 0.63240998, -0.81143878, 28.14326374, -112.21668611, -37.50384163, 59.8358837,
         -0.000636310182, 0.761300324, 0.0166730621, 0.292272043, 0.30933305, -0.09437577, 0.63324364, -0.79682517],
        [0.10070543, 0.18362721, 1.71401283, -0.79268193, 87.4279569, 59.15424688, -32.24268073, 53.92336999,
         -0.38431861, -0.53914067, 0.0073239, 0.0827787, 0.08148949, 0.15667018, 1.71437902, -0.78854299],
        # swing inside its negative law
        [-0.13538196, -0.02480018, 0.26008169, 0.44330993, 1.61027997, 0.85722611, 0.17559031, -89.3759888,
         -0.000678372914, -0.00154377982, -0.00112964468, -0.749551144, -0.13541587, -0.02487737, 0.26002521, 0.40583237],
    ]
)  # fmt: skip


def test_the_simulator_repeats_the_research_repositorys_recorded_steps():
    q, u, qd_next, q_next = np.split(LOGGED_STEPS, 4, axis=1)
    sim = PaperExcavator()
    sim.reset(q)
    obs = sim.step(u)
    np.testing.assert_allclose(obs[:, 4:], qd_next, atol=2e-8)
    np.testing.assert_allclose(obs[:, :4], q_next, atol=2e-8)


def test_swing_dead_zone_saturation_and_rounding():
    q = np.zeros(8)
    v = swing_velocity(np.array([51.4, 51.6, 76.6, 120.0, -66.4, -66.6, -89.6, -400.0]), q)
    assert v[0] == 0.0 and v[4] == 0.0  # rounded into the dead zone
    assert 0 < v[1] < 1 and -1 < v[5] < 0  # rounded out of it, onto the linear law
    assert v[2] == 1.0 and v[3] == 1.0 and v[6] == -1.0 and v[7] == -1.0  # saturated at ±1 rad/s


def test_a_joint_at_its_end_stop_does_not_move_further():
    sim = PaperExcavator()
    sim.reset(np.array([Q_MIN[0], Q_MAX[1], 0.5, 3.1]))
    obs = sim.step(np.array([1000.0, -1000.0, 0.0, 1000.0]))  # boom down, arm up: both beyond their stops
    assert obs[4] == 0.0 and obs[5] == 0.0
    assert obs[0] == Q_MIN[0] and obs[1] == Q_MAX[1]
    assert obs[3] == pytest.approx(3.1 + 0.05 - 2 * np.pi)  # the swing wraps at ±π


def test_batched_machines_run_as_if_each_were_alone():
    rng = np.random.default_rng(0)
    q0 = rng.uniform(Q_MIN[:3] + (-1.0,), Q_MAX[:3] + (1.0,), size=(5, 4))
    u = rng.uniform(-120, 120, size=(30, 5, 4))
    batched = PaperExcavator()
    batched.reset(q0)
    together = np.stack([batched.step(u_t) for u_t in u])
    for i in range(5):
        single = PaperExcavator()
        single.reset(q0[i])
        alone = np.stack([single.step(u_t[i]) for u_t in u])
        np.testing.assert_array_equal(together[:, i], alone)


def test_the_harder_variant_delays_lags_and_dead_bands_the_paper_simulator():
    rng = np.random.default_rng(1)
    q0 = rng.uniform(-0.3, 0.3, size=(3, 4))
    u = rng.uniform(-120, 120, size=(20, 3, 4))
    plain, delayed = PaperExcavator(), PaperExcavator(delay=2)
    plain.reset(q0), delayed.reset(q0)
    shifted = np.concatenate([np.zeros((2, 3, 4)), u[:-2]])  # the commands before the first act as 0
    np.testing.assert_array_equal(np.stack([delayed.step(u_t) for u_t in u]), np.stack([plain.step(s) for s in shifted]))
    banded = PaperExcavator(dead_band=30)
    banded.reset(q0)
    obs = banded.step(np.array([[30.0, -30.0, 29.0, 0.0]] * 3))
    assert np.all(obs[:, 4:7] == 0.0)  # boom, arm and bucket do not respond within the band
    plain.reset(q0)
    valve = plain.step(np.full((3, 4), 60.0))[:, 4:]
    lagged = PaperExcavator(lag=0.1)
    lagged.reset(q0)
    np.testing.assert_allclose(lagged.step(np.full((3, 4), 60.0))[:, 4:], (1 - np.exp(-0.5)) * valve)
    assert SystemSpec(system="paper", options=(("delay", 1), ("lag", 0.1), ("dead_band", 10))).open() is not None
    with pytest.raises(EfficientTrackError, match="delay must be a whole number of periods"):
        PaperExcavator(delay=-1)
    with pytest.raises(EfficientTrackError, match="lag must be a finite number ≥ 0"):
        PaperExcavator(lag=float("nan"))


def test_the_paper_plant_is_closed_with_its_own_pd_unless_told_otherwise():
    assert SystemSpec(plant="paper").pd_name == "paper"
    assert SystemSpec(plant="paper", pd="xe75").pd_name == "xe75"
    assert SystemSpec(plant="xe75").pd_name == "xe75"
    assert SystemSpec(plant="paper").to_dict()["pd"] == "paper"
    refs = generate_references(2, seed=3)
    as_system = track(SystemSpec(system="paper").open(), None, refs, progress=False)
    as_plant = track(SystemSpec(plant="paper").open(), None, refs, progress=False)
    for a, b in zip(as_system, as_plant, strict=True):
        np.testing.assert_array_equal(a.q, b.q)
    under_xe75_pd = track(SystemSpec(plant="paper", pd="xe75").open(), None, refs, progress=False)
    assert not np.array_equal(as_system[0].u, under_xe75_pd[0].u)
    assert PAPER_PD.c == 0.0


@pytest.mark.filterwarnings("ignore:.*Box observation space m.*infinity")
@pytest.mark.parametrize("env_id", [CLOSED_LOOP_ID, OPEN_LOOP_ID])
def test_both_loops_environments_run_on_it(env_id):
    refs = [Reference("short", generate_references(1, seed=4)[0].q[:30])]
    env = gymnasium.make(env_id, system="paper", refs=refs)
    obs, _ = env.reset(seed=0)
    steps, done = 0, False
    while not done:
        obs, reward, terminated, truncated, _ = env.step(np.zeros(4, dtype=np.float32))
        done, steps = terminated or truncated, steps + 1
    assert steps == 29 and np.all(np.isfinite(obs)) and np.isfinite(reward)


@pytest.mark.skipif(not TEST_REFS.is_dir(), reason=f"the paper's test references not found at {TEST_REFS}")
def test_pd_on_the_papers_test_references_gives_table_1s_pd_row():
    refs = load_references(TEST_REFS)
    records = track(SystemSpec(system="paper").open(), None, refs, progress=False)
    m = compute_metrics(records)
    assert m["episodes"] == 8
    table_1 = {"mae_deg": 2.73, "rmse_deg": 3.14, "fmae_deg": 2.93, "smt1_deg": 0.67, "smt2_deg": 0.70}
    for key, paper in table_1.items():
        assert m[key] == pytest.approx(paper, abs=0.005), key  # equal when rounded to the paper's 0.01°
    assert m["etd_mae_cm"] == pytest.approx(14.73, abs=0.05)
    assert m["etd_fmae_cm"] == pytest.approx(11.25, abs=0.05)

import sys
import types

import numpy as np
import pytest

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.systems import BatchedSystem, ClosedLoop, check_system, load_plant, load_system


class Integrator:
    """Unbatched plant: q̇ = 1e-3·u, one step per dt."""

    dt = 0.05

    def reset(self, q0):
        assert np.shape(q0) == (4,)
        self.q = np.array(q0, dtype=float)
        return np.concatenate([self.q, np.zeros(4)])

    def step(self, u):
        assert np.shape(u) == (4,)
        qd = 1e-3 * np.asarray(u)
        self.q = self.q + qd * self.dt
        return np.concatenate([self.q, qd])


class BadObs(Integrator):
    def step(self, u):
        return np.full(8, np.nan)


@pytest.fixture
def user_module(monkeypatch):
    module = types.ModuleType("user_machines")
    module.make_plant = lambda gain=1.0: Integrator()
    module.make_bad = lambda: ClosedLoop(BadObs())
    module.not_callable = 3
    monkeypatch.setitem(sys.modules, "user_machines", module)
    return module


def test_load_plant_from_import_path_and_wrap_with_pd(user_module):
    plant = load_plant("user_machines:make_plant", gain=2.0)
    assert plant.max_batch == 1
    obs = plant.reset(np.zeros((1, 4)))
    assert obs.shape == (1, 8)
    system = BatchedSystem(ClosedLoop(plant.system), name="pd")
    system.reset(np.zeros((1, 4)))
    obs = system.step(np.full((1, 4), 0.1))
    # The XE75 law: boom/arm/bucket move to smaller angles for positive error (sign −1), swing larger.
    assert np.all(np.sign(obs[0, :3]) == -1) and obs[0, 3] > 0
    assert system.last_command.shape == (1, 4)


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("nope", "unknown system 'nope'"),
        ("no_such_module_xyz:make", "cannot import module 'no_such_module_xyz'"),
        ("user_machines:missing", "has no callable 'missing'"),
        ("user_machines:not_callable", "has no callable 'not_callable'"),
    ],
)
def test_load_system_errors_name_the_spec(user_module, spec, message):
    with pytest.raises(EfficientTrackError, match=message):
        load_system(spec)


def test_bad_options_and_non_finite_observations_are_reported(user_module):
    with pytest.raises(EfficientTrackError, match="cannot be built with options"):
        load_plant("user_machines:make_plant", colour="red")
    system = load_system("user_machines:make_bad")
    system.reset(np.zeros((1, 4)))
    with pytest.raises(EfficientTrackError, match="system 'user_machines:make_bad': step returned a non-finite"):
        system.step(np.zeros((1, 4)))


def test_unbatched_system_refuses_a_batch_and_wrong_shapes():
    system = BatchedSystem(ClosedLoop(Integrator()), name="mine")
    with pytest.raises(EfficientTrackError, match="single machines only"):
        system.reset(np.zeros((3, 4)))
    system.reset(np.zeros((1, 4)))
    with pytest.raises(EfficientTrackError, match=r"step expects \(1, 4\)"):
        system.step(np.zeros((1, 3)))


def test_check_system_rejects_a_missing_dt():
    class NoDt:
        def reset(self, q0):
            return np.zeros(8)

        def step(self, q_ref):
            return np.zeros(8)

    with pytest.raises(EfficientTrackError, match="attribute 'dt'"):
        check_system(NoDt())
    check_system(ClosedLoop(Integrator()))

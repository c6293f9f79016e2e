"""The ILC oracle: its update law, its curve, its errors (a few seconds in all)."""

import json

import numpy as np
import pytest
import torch

from efficienttrack.baselines.curve import CURVE_FILE, training_run
from efficienttrack.baselines.ilc import (
    ILC_PRESETS,
    ILCSettings,
    identify_lead,
    ilc_settings,
    ilc_update,
    run_trial,
    train_ilc,
    trial_steps,
)
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.data.cycles import generate_references
from efficienttrack.data.metrics import compute_metrics
from efficienttrack.data.references import Reference
from efficienttrack.deploy.runtime import track
from efficienttrack.envs import evaluate
from efficienttrack.learn.policy import AdjustmentPolicy, save_policy
from efficienttrack.learn.settings import POLICY_PRESETS
from efficienttrack.systems.spec import SystemSpec
from toy_system import sine_refs

DELAY = 2
TOY_DELAYED = SystemSpec(system="toy_system:make", options=(("delay", DELAY),))
"""The toy first-order lag, answering its reference two steps late."""


def toy_refs():
    """Slow enough that the lag's correction stays inside the adjustment bound."""
    return [Reference(r.name, 0.3 * r.q) for r in sine_refs([60, 50], seed=2)]


def xe75_refs():
    """Two short loading-cycle pieces on the built-in xe75."""
    return [Reference(r.name, r.q[40:140]) for r in generate_references(2, seed=3)]


def maes(curve):
    return [p["metrics"]["mae_deg"] for p in curve]


def test_toy_error_falls_trial_by_trial_to_near_zero(tmp_path):
    refs = toy_refs()
    settings = ILCSettings(gain=1.0, lead=DELAY, cutoff_hz=None, trials=12)
    curve = train_ilc(training_run("closed", TOY_DELAYED, refs, refs, 10**6, 0, tmp_path), preset=settings)
    mae = maes(curve)
    assert len(mae) == 13
    assert all(b < a for a, b in zip(mae, mae[1:], strict=False)), mae
    # what is left: the first steps, before the delay lets a correction act
    assert mae[0] > 0.5 and mae[-1] < 0.02 * mae[0], mae


def test_the_lead_matters_on_the_delayed_toy(tmp_path):
    refs = toy_refs()
    right = train_ilc(training_run("closed", TOY_DELAYED, refs, refs, 10**6, 0, tmp_path / "a"),
                      preset=ILCSettings(gain=1.0, lead=DELAY, cutoff_hz=None, trials=6))  # fmt: skip
    none = train_ilc(training_run("closed", TOY_DELAYED, refs, refs, 10**6, 0, tmp_path / "b"),
                     preset=ILCSettings(gain=1.0, lead=0, cutoff_hz=None, trials=6))  # fmt: skip
    assert maes(right)[-1] < 0.5 * maes(none)[-1]


def test_the_lead_is_identified_from_trial_0_as_the_toys_delay(tmp_path):
    refs = toy_refs()
    correction = np.zeros((max(len(r) for r in refs) - 1, len(refs), 4))

    def lead(delay, gain):
        toy = SystemSpec(system="toy_system:make", options=(("delay", delay), ("gain", gain))).open()
        return identify_lead(run_trial(toy, refs, correction)[0])

    assert [lead(d, 1.0) for d in (0, DELAY, 5)] == [(0,) * 4, (DELAY,) * 4, (5,) * 4]  # a pure delay, exactly
    lagging = lead(0, 0.4)
    assert lead(5, 0.4) == tuple(x + 5 for x in lagging)  # a lag adds its own, the delay on top
    curve = train_ilc(training_run("closed", TOY_DELAYED, refs, refs, 10**6, 0, tmp_path), preset=ILCSettings(trials=8))
    assert maes(curve)[-1] < 0.1 * maes(curve)[0]
    assert json.loads((tmp_path / CURVE_FILE).read_text())["lead_identified"] == [x + DELAY for x in lagging]


def test_xe75_trials_lower_the_error_and_trial_0_is_pd(tmp_path):
    refs = xe75_refs()
    curve = train_ilc(training_run("closed", SystemSpec(), refs, refs, 10**6, 0, tmp_path), preset="tiny")
    pd = compute_metrics(evaluate(lambda obs: np.zeros((len(obs), 4)), refs, system=SystemSpec()))
    assert curve[0]["metrics"]["mae_deg"] == pytest.approx(pd["mae_deg"], rel=1e-9)
    mae = maes(curve)
    assert len(mae) == ILC_PRESETS["tiny"].trials + 1
    assert mae[-1] < 0.5 * mae[0], mae


def test_on_top_of_a_policy_trial_0_is_the_policy_deployed_and_the_trials_lower_its_error(tmp_path):
    refs = xe75_refs()
    torch.manual_seed(0)
    policy = AdjustmentPolicy(POLICY_PRESETS["tiny"])
    torch.nn.init.normal_(policy.pi_phi.body[-1].weight, std=0.2)  # an untrained policy that adjusts
    path = save_policy(policy, tmp_path / "policy.pt")
    curve = train_ilc(training_run("closed", SystemSpec(), refs, refs, 10**6, 0, tmp_path), preset="tiny", policy=path)
    deployed = compute_metrics(track(SystemSpec().open(), policy, refs, progress=False))
    pd = compute_metrics(evaluate(lambda obs: np.zeros((len(obs), 4)), refs, system=SystemSpec()))
    assert curve[0]["metrics"]["mae_deg"] == pytest.approx(deployed["mae_deg"], rel=1e-6)
    assert abs(deployed["mae_deg"] - pd["mae_deg"]) > 0.01 * pd["mae_deg"]  # the policy did adjust: trial 0 is not PD
    mae = maes(curve)
    assert all(b < a for a, b in zip(mae, mae[1:], strict=False)) and mae[-1] < 0.6 * mae[0], mae
    assert json.loads((tmp_path / CURVE_FILE).read_text())["policy"] == str(path)
    with pytest.raises(EfficientTrackError, match="missing.pt"):
        missing = training_run("closed", SystemSpec(), refs, refs, 10**6, 0, tmp_path / "b")
        train_ilc(missing, "tiny", policy=tmp_path / "missing.pt")


def test_curve_points_and_file(tmp_path):
    refs = toy_refs()
    per_trial = trial_steps(refs)
    assert per_trial == 59 + 49
    settings = ILCSettings(gain=1.0, lead=DELAY, cutoff_hz=None, trials=10)
    # the budget allows 4 trials; points recorded at the first trial reaching 1 and 3 · per_trial, besides trial 0
    curve = train_ilc(
        training_run("closed", TOY_DELAYED, refs[:1], refs, 4 * per_trial + 7, 5, tmp_path, [1, 3 * per_trial]), settings
    )
    assert [p["interaction_steps"] for p in curve] == [0, per_trial, 3 * per_trial]
    assert all(set(p) == {"interaction_steps", "wall_seconds", "metrics", "gradient_samples"} for p in curve)
    assert all(p["gradient_samples"] == 0 for p in curve)  # no gradient: corrections learned by the ILC law
    walls = [p["wall_seconds"] for p in curve]
    assert walls[0] >= 0 and walls == sorted(walls)
    saved = json.loads((tmp_path / CURVE_FILE).read_text())
    assert saved["method"] == "ilc" and saved["oracle"] is True and saved["loop"] == "closed" and saved["seed"] == 5
    assert saved["settings"]["lead"] == [DELAY] * 4 and saved["budget"] == 4 * per_trial + 7
    assert [p["metrics"] for p in saved["curve"]] == [p["metrics"] for p in curve]
    full = train_ilc(training_run("closed", TOY_DELAYED, refs[:1], refs, 4 * per_trial + 7, 5, tmp_path / "all"), settings)
    assert [p["interaction_steps"] for p in full] == [k * per_trial for k in range(5)]  # the budget ends it at trial 4


def test_deterministic(tmp_path):
    refs = xe75_refs()
    settings = ILCSettings(trials=2)
    one = train_ilc(training_run("closed", SystemSpec(), refs, refs, 10**6, 0, tmp_path / "a"), settings)
    two = train_ilc(training_run("closed", SystemSpec(), refs, refs, 10**6, 1, tmp_path / "b"), settings)
    assert [p["metrics"] for p in one] == [p["metrics"] for p in two]


def test_update_law():
    error = np.zeros((10, 1, 4))
    error[6, 0] = [0.1, 0.2, -0.3, 1.0]
    settings = ILCSettings(gain=(1.0, 0.5, 0.5, 2.0), lead=(2, 2, 0, 2), cutoff_hz=None)
    bound = np.array([0.15, 0.3, 0.4, 0.4])
    new = ilc_update(np.zeros_like(error), error, settings, bound, 0.05)
    expected = np.zeros_like(error)
    expected[4, 0, [0, 1, 3]] = [0.1, 0.1, 0.4]  # two steps earlier, times the gain, the swing clipped at its bound
    expected[6, 0, 2] = -0.15  # lead 0: the same step
    np.testing.assert_allclose(new, expected)
    smooth = ilc_update(np.zeros((50, 2, 4)), np.ones((50, 2, 4)) * 0.01, ILCSettings(gain=1.0, lead=0), bound, 0.05)
    np.testing.assert_allclose(smooth[:40], 0.01, atol=1e-9)  # the zero-phase filter leaves a constant alone


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"gain": -1.0}, "ILCSettings.gain must be a list of 4 finite numbers > 0"),
        ({"gain": (1.0, 1.0)}, "ILCSettings.gain must be a list of 4"),
        ({"lead": -1}, "ILCSettings.lead must be auto or 4 integers ≥ 0"),
        ({"lead": (1, 2, 3)}, "ILCSettings.lead must be a list of 4 integers"),
        ({"cutoff_hz": 0.0}, "ILCSettings.cutoff_hz must be a finite number > 0"),
        ({"trials": 0}, "ILCSettings.trials must be an integer ≥ 1"),
        ({"filter_order": 0}, "ILCSettings.filter_order must be an integer ≥ 1"),
    ],
)
def test_bad_settings(changes, message):
    with pytest.raises(EfficientTrackError, match=message):
        ILCSettings(**changes)


def test_bad_input(tmp_path):
    refs = toy_refs()
    good = {"loop": "closed", "system": TOY_DELAYED, "train_refs": refs, "test_refs": refs, "budget": 10**6, "seed": 0,
            "folder": tmp_path, "preset": "tiny"}  # fmt: skip
    cases = [
        ({"loop": "open", "system": SystemSpec()}, "closed loop only"),  # a system with a plant: the open loop can run
        ({"validation_refs": refs}, "validation_refs: the ILC oracle learns its corrections on the test references"),
        ({"loop": "sideways"}, "unknown"),
        ({"preset": "huge"}, "preset 'huge'"),
        ({"budget": 50}, "less than one ILC trial"),
        ({"budget": 0}, "budget"),
        ({"seed": -1}, "seed"),
        ({"system": "xe75"}, "SystemSpec"),
        ({"test_refs": []}, "test_refs: no references"),
        ({"test_refs": [Reference("short", refs[0].q[:3])]}, "needs at least 4"),
        ({"eval_at": [0]}, "eval_at"),
        ({"preset": ILCSettings(cutoff_hz=10.0)}, "Nyquist"),
        ({"folder": tmp_path / CURVE_FILE / "x", "budget": 10**6}, "folder"),
    ]
    (tmp_path / CURVE_FILE).write_text("{}")
    for changes, message in cases:
        with pytest.raises(EfficientTrackError, match=message):
            args = {**good, **changes}
            train_ilc(preset=args.pop("preset"), run=training_run(**args))
    assert ilc_settings("cpu") is ILC_PRESETS["cpu"]

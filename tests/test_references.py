from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from efficienttrack.cli import app
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.joints import DT
from efficienttrack.data.cycles import CYCLE_PRESETS, CycleConfig, generate_references, reference_stats
from efficienttrack.data.references import (
    Reference,
    load_references,
    save_references,
)
from efficienttrack.workflow.plots import plot_references

REAL_REFS = Path(__file__).resolve().parents[2] / "shared" / "data" / "references" / "train"


@pytest.fixture(scope="module")
def generated():
    return generate_references(40, 0)


# --- generator ------------------------------------------------------------------------------------


def test_generator_is_deterministic_by_seed(generated):
    again = generate_references(40, 0)
    assert [r.name for r in again] == [f"ref_{i:02d}" for i in range(1, 41)]
    assert all(np.array_equal(a.q, b.q) for a, b in zip(generated, again, strict=True))
    other = generate_references(40, 1)
    assert not any(np.array_equal(a.q[:50], b.q[:50]) for a, b in zip(generated, other, strict=True))


def test_generated_shape_duration_and_stillness():
    refs = generate_references(300, 3)
    assert len(refs) == 300 and refs[-1].name == "ref_300"
    durations = np.array([r.duration for r in refs])
    assert durations.min() >= 15.0 and durations.max() <= 25.0
    assert durations.std() > 1.0  # the durations really vary
    for ref in refs:
        assert ref.q.shape == (round(ref.duration / DT) + 1, 4) and ref.q.dtype == np.float64
        assert np.isfinite(ref.q).all()
        assert np.abs(np.diff(ref.q[:8], axis=0)).max() == 0.0  # start_hold ≥ 0.4 s: still at the start
        assert np.abs(np.diff(ref.q[-6:], axis=0)).max() < 1e-12  # end_hold ≥ 0.3 s: still at the end
        assert abs(ref.q[-1, 3] - ref.q[0, 3]) <= 0.12 + 1e-9  # back over the truck (swing_back_offset)


def test_generated_smoothness_bounds():
    cfg = CYCLE_PRESETS["xe75"]
    refs = generate_references(300, 4)
    speed = np.max([np.abs(np.diff(r.q, axis=0)).max(axis=0) for r in refs], axis=0) / DT
    accel = np.max([np.abs(np.diff(r.q, n=2, axis=0)).max(axis=0) for r in refs], axis=0) / DT**2
    # plateau speeds are the config maxima; a smoothstep ramp of time τ peaks at 1.5·v/τ
    v_max = np.array(
        [
            max(cfg.boom_down_speed[1], cfg.boom_up_speed[1]),
            max(cfg.arm_out_speed[1], cfg.arm_in_speed[1]),
            max(cfg.curl_speed[1], cfg.dump_speed[1]),
            max(cfg.swing_out_speed[1], cfg.swing_back_speed[1]),
        ]
    )
    tau_min = np.array([cfg.ramp_time[0]] * 3 + [cfg.swing_ramp_time[0]])
    assert (speed <= 1.02 * v_max).all(), speed
    assert (speed >= 0.8 * v_max).all(), speed  # the fast strokes do happen
    assert (accel <= 1.1 * 1.5 * v_max / tau_min).all(), accel


def test_generator_config_validation():
    with pytest.raises(EfficientTrackError, match="n: need 1 to 10,000 references, got 0"):
        generate_references(0, 0)
    with pytest.raises(EfficientTrackError, match="cycle preset 'nope'"):
        generate_references(3, 0, "nope")
    with pytest.raises(EfficientTrackError, match="CycleConfig.pile_boom"):
        CycleConfig(pile_boom=(0.5, 0.3))
    with pytest.raises(EfficientTrackError, match="CycleConfig.pile_arm"):
        CycleConfig(pile_arm=("-1", "0"))
    with pytest.raises(EfficientTrackError, match="CycleConfig.dump_speed: must be positive"):
        CycleConfig(dump_speed=(0.0, 1.0))
    with pytest.raises(EfficientTrackError, match="almost never fit"):
        generate_references(2, 0, CycleConfig(duration=(5.0, 6.0)))
    custom = generate_references(3, 0, CycleConfig(duration=(10.0, 40.0)))
    assert len(custom) == 3


# --- statistics against the real XE75 references ----------------------------------------------------


def test_reference_stats_known_answer():
    t = np.arange(101) * DT  # 5 s
    q = np.zeros((101, 4))
    q[:, 0] = 0.2 * t  # constant speed 0.2 rad/s, span 1.0 rad
    q[:, 3] = -0.1 * t**2  # constant acceleration -0.2 rad/s²
    stats = reference_stats([Reference("a", q), Reference("b", q[:51])])
    assert stats.n == 2 and stats.duration == pytest.approx(3.75) and stats.duration_range == pytest.approx((2.5, 5.0))
    np.testing.assert_allclose(stats.q_min, [0, 0, 0, -2.5])
    np.testing.assert_allclose(stats.q_max, [1.0, 0, 0, 0])
    np.testing.assert_allclose(stats.span, [0.75, 0, 0, (2.5 + 0.625) / 2])
    np.testing.assert_allclose(stats.peak_speed, [0.2, 0, 0, (0.995 + 0.495) / 2], atol=1e-9)
    np.testing.assert_allclose(stats.peak_accel, [0, 0, 0, 0.2], atol=1e-9)


def test_generator_statistics_resemble_the_real_references(generated):
    if not REAL_REFS.is_dir():
        pytest.skip(f"real XE75 references not found at {REAL_REFS} (shared data absent)")
    real, gen = reference_stats(load_references(REAL_REFS)), reference_stats(generated)
    assert real.n == 40
    assert gen.duration == pytest.approx(real.duration, rel=0.15)
    extent = real.q_max - real.q_min  # set extremes: within 15 % of the real per-joint extent
    assert (np.abs(gen.q_min - real.q_min) <= 0.15 * extent).all(), (gen.q_min, real.q_min)
    assert (np.abs(gen.q_max - real.q_max) <= 0.15 * extent).all(), (gen.q_max, real.q_max)
    for field in ("span", "peak_speed", "peak_accel"):  # medians over episodes: within ±35 %
        ratio = getattr(gen, field) / getattr(real, field)
        assert (np.abs(ratio - 1) <= 0.35).all(), (field, ratio)


# --- IO and validation -------------------------------------------------------------------------------


def test_save_load_round_trip_npy_and_csv(tmp_path, generated):
    paths = save_references(generated[:3][::-1], tmp_path)
    assert [p.name for p in paths] == ["ref_03.npy", "ref_02.npy", "ref_01.npy"]
    header = tmp_path / "b_header.csv"
    header.write_text("boom,arm,bucket,swing\n" + "\n".join(",".join(repr(float(x)) for x in row) for row in generated[3].q))
    plain = tmp_path / "a_plain.csv"
    np.savetxt(plain, generated[4].q, delimiter=",", fmt="%.17g")
    (tmp_path / "notes.txt").write_text("ignored")
    loaded = load_references(tmp_path)
    assert [r.name for r in loaded] == ["a_plain", "b_header", "ref_01", "ref_02", "ref_03"]
    for ref, src in zip(loaded, [generated[4], generated[3], *generated[:3]], strict=True):
        np.testing.assert_array_equal(ref.q, src.q)
    single = load_references([tmp_path / "ref_02.npy"])
    assert len(single) == 1 and np.array_equal(single[0].q, generated[1].q)
    assert load_references(str(tmp_path / "ref_01.npy"))[0].name == "ref_01"
    assert not single[0].q.flags.writeable


def test_real_references_load():
    if not REAL_REFS.is_dir():
        pytest.skip(f"real XE75 references not found at {REAL_REFS} (shared data absent)")
    refs = load_references(REAL_REFS)
    assert [r.name for r in refs][:2] == ["ref_01", "ref_02"] and len(refs) == 40
    assert min(len(r) for r in refs) == 369 and max(len(r) for r in refs) == 521


def _write_npy(tmp_path, name, arr):
    path = tmp_path / name
    np.save(path, arr)
    return path


@pytest.mark.parametrize(
    ("arr", "message"),
    [
        (np.zeros((10, 3)), r"shape \(T, 4\)"),
        (np.zeros((1, 4)), "at least 2 samples"),
        (np.array([[0.0, 0, 0, 0], [0, np.nan, 0, 0]]), "NaN or inf"),
        (np.tile([[10.0, -30.0, 90.0, 45.0]], (5, 1)), "looks like degrees"),
        (np.array([[0.0, 0, 0, 0], [0, 0, 0.1, 0], [0, 0, 0.8, 0]]), "bucket jumps 0.7 rad between samples 1 and 2"),
        (np.array([["a", "b", "c", "d"]] * 3), "dtype <U1, expected real floating-point numbers"),
    ],
)
def test_validation_errors_name_the_file(tmp_path, arr, message):
    path = _write_npy(tmp_path, "bad.npy", arr)
    with pytest.raises(EfficientTrackError, match=message) as info:
        load_references(tmp_path)
    assert str(path) in str(info.value)


def test_wrapped_steps_across_pi_are_fine():
    q = np.zeros((3, 4))
    q[:, 3] = [np.pi - 0.01, -np.pi + 0.01, -np.pi + 0.03]
    assert Reference("wrap", q).q.shape == (3, 4)


def test_file_level_errors(tmp_path):
    with pytest.raises(EfficientTrackError, match="no such file or folder"):
        load_references(tmp_path / "missing")
    with pytest.raises(EfficientTrackError, match="no reference files"):
        load_references(tmp_path)
    with pytest.raises(EfficientTrackError, match="no reference files given"):
        load_references([])
    (tmp_path / "x.txt").write_text("1,2,3,4")
    with pytest.raises(EfficientTrackError, match="unsupported reference file type"):
        load_references([tmp_path / "x.txt"])
    np.save(tmp_path / "pickled.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(EfficientTrackError, match="pickled.npy: holds Python objects"):
        load_references([tmp_path / "pickled.npy"])
    (tmp_path / "words.csv").write_text("boom,arm,bucket,swing\n0,0,zero,0\n")
    with pytest.raises(EfficientTrackError, match="words.csv: expected plain numeric CSV"):
        load_references([tmp_path / "words.csv"])
    (tmp_path / "three.csv").write_text("0,0,0\n0,0,0\n")
    with pytest.raises(EfficientTrackError, match=r"three.csv: reference must have shape \(T, 4\)"):
        load_references([tmp_path / "three.csv"])
    dup = tmp_path / "dup"
    dup.mkdir()
    np.save(dup / "r.npy", np.zeros((3, 4)))
    np.savetxt(dup / "r.csv", np.zeros((3, 4)), delimiter=",")
    with pytest.raises(EfficientTrackError, match="'r' was already read"):
        load_references(dup)
    with pytest.raises(EfficientTrackError, match="reference name = .../escape. cannot be a file name"):
        save_references([Reference("../escape", np.zeros((3, 4)))], tmp_path)
    with pytest.raises(EfficientTrackError, match="two references are named 'a'"):
        save_references([Reference("a", np.zeros((3, 4)))] * 2, tmp_path / "out")


def test_empty_damaged_and_oversized_reference_files(tmp_path):
    (tmp_path / "zero.npy").write_bytes(b"")
    with pytest.raises(EfficientTrackError, match=r"zero.npy: empty file \(0 bytes\)"):
        load_references(tmp_path / "zero.npy")
    (tmp_path / "zero.npy").unlink()
    (tmp_path / "zero.csv").write_bytes(b"")
    with pytest.raises(EfficientTrackError, match="zero.csv: empty file, no reference samples"):
        load_references(tmp_path / "zero.csv")
    (tmp_path / "header.csv").write_text("boom,arm,bucket,swing\n")
    with pytest.raises(EfficientTrackError, match="header.csv: no rows, no reference samples"):
        load_references(tmp_path / "header.csv")
    np.save(tmp_path / "flags.npy", np.zeros((5, 4), bool))
    with pytest.raises(EfficientTrackError, match="flags.npy: has dtype bool, expected real floating-point numbers"):
        load_references(tmp_path / "flags.npy")
    header = "{'descr': '<f8', 'fortran_order': False, 'shape': (90000000, 4), }"
    (tmp_path / "huge.npy").write_bytes(
        b"\x93NUMPY\x01\x00" + len(header + "\n").to_bytes(2, "little") + header.encode() + b"\n"
    )
    with pytest.raises(EfficientTrackError, match=r"huge.npy: declares a float64 array of shape \(90000000, 4\)"):
        load_references(tmp_path / "huge.npy")
    with pytest.raises(EfficientTrackError, match="reference name = 'a\\\\x00b' cannot be a file name: it holds a NUL"):
        save_references([Reference("a\x00b", np.zeros((3, 4)))], tmp_path / "out")


# --- plot and CLI ------------------------------------------------------------------------------------


@pytest.mark.figures
def test_plot_references_writes_png(tmp_path, generated):
    path = plot_references(generated[:5], tmp_path / "figs" / "refs.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.figures
def test_cli_refs_generate_and_plot(tmp_path):
    runner = CliRunner()
    result = runner.invoke(app, ["refs", "generate", "--n", "3", "--seed", "2", "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in tmp_path.glob("*.npy")) == ["ref_01.npy", "ref_02.npy", "ref_03.npy"]
    for ref, expected in zip(load_references(tmp_path), generate_references(3, 2), strict=True):
        np.testing.assert_array_equal(ref.q, expected.q)
    result = runner.invoke(app, ["refs", "plot", str(tmp_path)])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "references.png").stat().st_size > 10_000

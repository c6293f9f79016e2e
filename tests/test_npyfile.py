"""Crafted .npy/.npz files: every one gives one EfficientTrackError naming file and field, none expands beyond the bound."""

import io
import zipfile

import numpy as np
import numpy.lib.format as npy_format
import pytest

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import check_file_name
from efficienttrack.core.npyfile import MAX_EXPANDED_BYTES, read_npy, read_npz, read_pickled_npy

RECONSTRUCT = np.ndarray.__reduce__(np.empty(0))[0]


def npy_bytes(shape, descr="<f8", data=b""):
    """A .npy header declaring ``shape``, followed by ``data`` (however short)."""
    buffer = io.BytesIO()
    npy_format.write_array_header_1_0(buffer, {"descr": descr, "fortran_order": False, "shape": shape})
    return buffer.getvalue() + data


def array_bytes(array):
    buffer = io.BytesIO()
    np.save(buffer, array)
    return buffer.getvalue()


def write_zip(path, members, compression=zipfile.ZIP_DEFLATED):
    with zipfile.ZipFile(path, "w", compression) as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    return path


def test_round_trip_and_fortran_order(tmp_path):
    a = np.arange(12.0).reshape(3, 4)
    np.save(tmp_path / "c.npy", a)
    np.save(tmp_path / "f.npy", np.asfortranarray(a))
    np.savez_compressed(tmp_path / "z.npz", a=a, s=np.array("text"))
    np.testing.assert_array_equal(read_npy(tmp_path / "c.npy"), a)
    np.testing.assert_array_equal(read_npy(tmp_path / "f.npy"), a)
    arrays = read_npz(tmp_path / "z.npz", kinds={"s": "U"})
    np.testing.assert_array_equal(arrays["a"], a)
    assert str(arrays["s"]) == "text" and arrays["a"].flags.writeable


def test_a_huge_declared_shape_is_refused_before_allocating(tmp_path):
    path = tmp_path / "huge.npy"
    path.write_bytes(npy_bytes((80_000_000, 4), data=b"\0" * 64))
    with pytest.raises(EfficientTrackError, match=r"huge.npy: declares a float64 array of shape \(80000000, 4\).*MAX_EXP"):
        read_npy(path)
    write_zip(tmp_path / "huge.npz", {"q.npy": npy_bytes((80_000_000, 4), data=b"\0" * 64)})
    with pytest.raises(EfficientTrackError, match=r"huge.npz: field 'q': declares a float64 array of shape \(80000000, 4\)"):
        read_npz(tmp_path / "huge.npz")


def test_a_zip_bomb_is_refused_by_its_declared_size(tmp_path):
    """A small archive whose member inflates past the bound (as the probe's 665 KB npz expanding to 640 MB)."""
    rows = MAX_EXPANDED_BYTES // 32 + 2**16
    path = tmp_path / "bomb.npz"
    with (
        zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as archive,
        archive.open("q.npy", "w", force_zip64=True) as f,
    ):
        f.write(npy_bytes((rows, 4)))
        for _ in range(rows // 2**16):
            f.write(bytes(32 * 2**16))
    assert path.stat().st_size < 2**20
    with pytest.raises(EfficientTrackError, match=r"bomb.npz: its members expand to 130.0 MiB, more than the 128.0 MiB"):
        read_npz(path)


def test_a_header_lying_about_its_member_size_is_refused(tmp_path):
    """The member is small, its header declares more data than the member holds: refused before allocating."""
    write_zip(tmp_path / "lie.npz", {"q.npy": npy_bytes((1000, 4), data=b"\0" * 32)})
    with pytest.raises(EfficientTrackError, match="lie.npz: field 'q': declares a float64 array of shape"):
        read_npz(tmp_path / "lie.npz")


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"", r"empty file \(0 bytes\)"),
        (npy_bytes((10, 4), data=b"\0" * 100), "not a readable .npy array .*holds 100 bytes of data, its header declares 320"),
        (npy_bytes((2, 4), data=b"\0" * 100), r"not a readable .npy array .*holds 65\+ bytes of data"),
        (b"\x93NUMPY\x09\x00" + b"\0" * 20, "not a readable .npy array"),
        (np.random.default_rng(0).bytes(300), "not a readable .npy array"),
        (array_bytes(np.zeros((3, 4), bool)), "has dtype bool, expected real floating-point numbers"),
        (array_bytes(np.zeros((3, 4), complex)), "has dtype complex128, expected real floating-point numbers"),
        (npy_bytes((3,), descr="|O"), r"holds Python objects \(pickled data\), refused"),
    ],
)
def test_bad_npy_files_are_clear_errors(tmp_path, content, message):
    path = tmp_path / "bad.npy"
    path.write_bytes(content)
    with pytest.raises(EfficientTrackError, match=f"bad.npy: {message}"):
        read_npy(path)


def test_a_huge_header_and_damaged_members_name_the_field(tmp_path):
    header = "{'descr': '<f8', 'fortran_order': False, 'shape': (3, 4), }" + " " * 200_000 + "\n"
    big = b"\x93NUMPY\x02\x00" + len(header).to_bytes(4, "little") + header.encode() + bytes(96)
    write_zip(tmp_path / "header.npz", {"t.npy": array_bytes(np.zeros(3)), "q.npy": big})
    with pytest.raises(EfficientTrackError, match="header.npz: field 'q': not readable .*Header info length"):
        read_npz(tmp_path / "header.npz")
    good = array_bytes(np.random.default_rng(0).normal(size=(200, 4)))
    raw = bytearray(write_zip(tmp_path / "zlib.npz", {"q.npy": good}).read_bytes())
    start = raw.index(b"q.npy") + len("q.npy")
    raw[start + 40 : start + 80] = b"\xff" * 40
    (tmp_path / "zlib.npz").write_bytes(bytes(raw))
    with pytest.raises(EfficientTrackError, match=r"zlib.npz: field 'q': (damaged compressed data \(zlib|damaged \(Bad CRC)"):
        read_npz(tmp_path / "zlib.npz")
    write_zip(tmp_path / "other.npz", {"notes.txt": b"hello"})
    with pytest.raises(EfficientTrackError, match="other.npz: member 'notes.txt' is not a .npy array"):
        read_npz(tmp_path / "other.npz")
    write_zip(tmp_path / "kinds.npz", {"meta_json.npy": array_bytes(np.zeros(3))})
    with pytest.raises(EfficientTrackError, match="kinds.npz: field 'meta_json': has dtype float64, expected a text string"):
        read_npz(tmp_path / "kinds.npz", kinds={"meta_json": "U"})


# ------------------------------------------------------------------------------------- pickled object arrays


class NdarrayCall:
    """Asks the unpickler to call ``numpy.ndarray(shape)``: 690 MB from a few hundred bytes."""

    def __reduce__(self):
        return (np.ndarray, ((90_000_000,), "f8"))


class BigReconstruct:
    def __reduce__(self):
        return (RECONSTRUCT, (np.ndarray, (90_000_000,), b"f8"))


class BigState:
    def __reduce__(self):
        return (RECONSTRUCT, (np.ndarray, (0,), b"b"), (1, (90_000_000,), np.dtype("f8"), False, b""))


class ShortObjectList:
    """An object array whose state lists fewer items than its shape: numpy reads past the list (a segfault)."""

    def __reduce__(self):
        return (RECONSTRUCT, (np.ndarray, (0,), b"b"), (1, (3,), np.dtype("O"), False, [1]))


class SubarrayDtype:
    def __reduce__(self):
        return (np.dtype, (("f8", (90_000_000,)),))


def pickled_npy(path, content):
    holder = np.empty((), dtype=object)
    holder[()] = content
    np.save(path, holder, allow_pickle=True)
    return path


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (NdarrayCall(), "not callable"),
        (BigReconstruct(), "refused an array reconstruction other than numpy's own"),
        (BigState(), r"declares a float64 array of shape \(90000000,\) \(686.6 MiB\), more than the 128.0 MiB"),
        (ShortObjectList(), r"an array of shape \(3,\) and dtype object holds data of another size"),
        (SubarrayDtype(), "refused a structured dtype"),
    ],
)
def test_a_pickle_cannot_allocate_or_read_past_its_data(tmp_path, content, message):
    path = pickled_npy(tmp_path / "crafted.npy", {"js": [content], "time": [0.0]})
    assert path.stat().st_size < 600
    with pytest.raises(EfficientTrackError, match=f"crafted.npy: .*{message}"):
        read_pickled_npy(path, "an episode")


def test_pickled_arrays_and_plain_containers_still_load(tmp_path):
    content = {"js": [np.arange(4.0), np.ones(4)], "time": [0.0, 0.05], "name": "x", "ints": np.arange(3)}
    loaded = read_pickled_npy(pickled_npy(tmp_path / "ok.npy", content), "an episode")
    assert loaded.keys() == content.keys() and loaded["name"] == "x" and loaded["time"] == [0.0, 0.05]
    np.testing.assert_array_equal(loaded["js"][1], np.ones(4))
    np.save(tmp_path / "plain.npy", np.zeros((3, 4)))
    with pytest.raises(EfficientTrackError, match=r"plain.npy: holds a float64 array of shape \(3, 4\), not an episode"):
        read_pickled_npy(tmp_path / "plain.npy", "an episode")


# ------------------------------------------------------------------------------------------------- file names


@pytest.mark.parametrize(
    ("name", "problem"),
    [
        ("../../x", "holds a path separator"),
        ("/abs/x", "holds a path separator"),
        ("a\\b", "holds a path separator"),
        ("..", "starts with a dot"),
        (".hidden", "starts with a dot"),
        ("a\x00b", "holds a NUL or control character"),
        ("", "is empty"),
        (7, "is a int, not a string"),
        ("x" * 201, "is longer than 200 bytes"),
    ],
)
def test_file_names_from_file_contents_stay_inside_the_folder(name, problem):
    with pytest.raises(EfficientTrackError, match=f"^src.npz: field 'meta' = .* cannot be a file name: it {problem}"):
        check_file_name(name, "src.npz: field 'meta'")


def test_plain_names_pass():
    for name in ("ref_01", "zc_interp_train1_2024_10_31_11_28_04_p2", "run 1 (copy)", "Ω-mode"):
        assert check_file_name(name, "x") == name

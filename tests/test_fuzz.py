"""Malformed bytes never escape a loader as anything but one EfficientTrackError naming the file (issue 29).

For every file format the package reads (:data:`FORMATS`), a good file is built here (never read from elsewhere), and
mutants of it are made at a fixed seed: byte flips, bit flips, truncations, insertions, deletions, duplicated chunks,
edits of the header (a ``.npy`` header's text, a CSV's header row, a YAML key line), and for the zip archives
(``.npz``, ``.pt``) corrupted member data written back as a valid zip and damaged fields of the zip records. Each
mutant is loaded through the public loader; it must either load or raise
:class:`~efficienttrack.core.errors.EfficientTrackError` whose message names the file. Any other exception (and a
``RuntimeWarning`` from the package, an error under this suite's warning filter) fails the test with the mutant's
index, how it was made and its traceback.

Mutants per format: 500 (:data:`MUTANTS`), and 200 for the two checkpoint formats (:data:`CHECKPOINT_MUTANTS`,
~1.8 ms a mutant where the others take ~0.4-1.5 ms): this file takes ~8 s beside another test worker, inside its ~10 s
share of the suite (1,000 and 400 took ~16 s there). The issue's 3,000 per format run by hand with
``python benchmarks/fuzz_loaders.py --mutants 3000`` (the same :func:`sweep`). :data:`FOUND` keeps each kind of escape
the sweep found as a test of its own.
"""

from __future__ import annotations

import io
import json
import pickle
import re
import struct
import time
import traceback
import tracemalloc
import warnings
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import numpy.lib.format as npy_format
import pytest
import torch

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.data.records import UPSTREAM_KEYS, load_record, load_records, save_csv, save_records
from efficienttrack.data.references import Reference, load_references, save_references
from efficienttrack.learn.dynamics import ClosedLoopModel, load_model, save_model
from efficienttrack.learn.policy import AdjustmentPolicy, load_policy, save_policy
from efficienttrack.learn.settings import MODEL_PRESETS, POLICY_PRESETS
from efficienttrack.systems.limits import GuardLimits
from test_records import make_record

SEED = 29
"""The sweep's seed (the issue's number); mutant ``i`` of a format is made from ``(SEED, format index, i)``."""
MUTANTS = 500
"""Mutants per format in this test (the benchmark runs 3,000 or more)."""
CHECKPOINT_MUTANTS = 200
"""Mutants per checkpoint format: ``torch.load`` and building the network take ~1.7 ms a mutant, 3x the others."""


# --------------------------------------------------------------------------------------------- good files


def _record(steps: int = 24):
    return make_record(steps=steps, name="good")


def _episode_npz(folder: Path) -> Path:
    return save_records([_record()], folder)[0]


def _episode_csv(folder: Path) -> Path:
    return save_csv(_record(), folder / "good.csv")


def _upstream_episode(steps: int = 12) -> dict[str, list]:
    """An episode as the research repository saved it: per-step (4,) float64 arrays, and floats for ``time``."""
    rng = np.random.default_rng(0)
    q = np.cumsum(rng.normal(0, 0.01, (steps, 4)), axis=0)
    columns = {"target": q + 0.01, "real_target": q + 0.02, "js": q, "jv": rng.normal(0, 0.1, (steps, 4))}
    episode: dict[str, list] = {key: list(value) for key, value in columns.items()}
    episode["time"] = [0.05 * i for i in range(steps)]
    episode["action"] = list(rng.uniform(-1000, 1000, (steps, 4)))
    assert set(episode) == set(UPSTREAM_KEYS)
    return episode


def _upstream_npy(folder: Path) -> Path:
    """The upstream ``.npy``: a 0-d object array pickled at protocol 3 by numpy 1 (``numpy.core`` names), as its files."""
    holder = np.empty((), dtype=object)
    holder[()] = _upstream_episode()
    pickled = pickle.dumps(holder, protocol=3).replace(b"numpy._core.multiarray", b"numpy.core.multiarray")
    path = folder / "good.npy"
    with path.open("wb") as f:
        npy_format.write_array_header_1_0(f, {"descr": "|O", "fortran_order": False, "shape": ()})
        f.write(pickled)
    return path


def _upstream_csv(folder: Path) -> Path:
    """The upstream ``.csv``: header ``target,real_target,js,jv,time,action``, vectors printed by numpy, unquoted."""
    episode = _upstream_episode()
    rows = [",".join(str(episode[key][i]) for key in episode) for i in range(12)]
    path = folder / "good.csv"
    path.write_text("\n".join([",".join(episode), *rows]) + "\n")
    return path


def _reference_q(steps: int = 24) -> np.ndarray:
    return 0.3 * np.sin(np.linspace(0, 2, steps))[:, None] + np.array([0.1, -0.2, 0.3, 0.0])


def _reference_npy(folder: Path) -> Path:
    return save_references([Reference("good", _reference_q())], folder)[0]


def _reference_csv(folder: Path) -> Path:
    path = folder / "good.csv"
    np.savetxt(path, _reference_q(), delimiter=",", header="boom,arm,bucket,swing", comments="", fmt="%.10g")
    return path


def _checkpoint(save: Callable, network: object, folder: Path) -> Path:
    """A checkpoint and its config; the config's weights digest is dropped, so a mutant that still loads as tensors
    reaches the checks of the weights themselves (NaN/inf, sizes) instead of stopping at the digest."""
    path = save(network, folder / "good.pt")
    config = path.with_suffix(".json")
    config.write_text(json.dumps({**json.loads(config.read_text()), "weights_sha256": None}))
    return path


def _model_pt(folder: Path) -> Path:
    with torch.random.fork_rng(devices=[]):  # the same weights, hence the same mutants, in every run
        torch.manual_seed(0)
        return _checkpoint(save_model, ClosedLoopModel(MODEL_PRESETS["tiny"]), folder)


def _policy_pt(folder: Path) -> Path:
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        return _checkpoint(save_policy, AdjustmentPolicy(POLICY_PRESETS["tiny"]), folder)


def _limits_yaml(folder: Path) -> Path:
    path = folder / "good.yaml"
    path.write_text(
        "q_min: [-1.2, -2.0, -2.5, -3.14159]  # rad\n"
        "q_max: [1.2, 0.5, 2.5, 3.14159]\n"
        "max_adjust: [0.15, 0.3, 0.4, 0.4]\n"
        "max_adjust_rate: [0.075, 0.15, 0.2, 0.2]\n"
        "max_speed: [3.0, 3.0, 4.0, 2.0]\n"
        "stale_steps: 5\n"
    )
    return path


def _limits_json(folder: Path) -> Path:
    path = folder / "good.json"
    path.write_text(json.dumps(GuardLimits(stale_steps=5).to_dict(), indent=1))
    return path


def _load_checkpoint(load: Callable) -> Callable[[Path], object]:
    return lambda path: load(path, device="cpu")


# ------------------------------------------------------------------------------------------------ formats


@dataclass(frozen=True)
class Format:
    """One file format: how to build a good file, how to load one, and what its header and members are."""

    name: str
    build: Callable[[Path], Path]
    """Writes a good file (and what lies beside it, e.g. a checkpoint's config) into a folder; returns its path."""
    load: Callable[[Path], object]
    """The public loader; a mutant is written over the good file's path, so a sidecar config stays valid."""
    kind: str
    """``"npy"``, ``"npz"``, ``"pt"`` or ``"text"``: which header and member edits apply."""
    checkpoint: bool = False


FORMATS = (
    Format("episode .npz", _episode_npz, load_record, "npz"),
    Format("episode .csv", _episode_csv, lambda path: load_records([path]), "text"),
    Format("upstream episode .npy", _upstream_npy, load_record, "npy"),
    Format("upstream episode .csv", _upstream_csv, load_record, "text"),
    Format("reference .npy", _reference_npy, load_references, "npy"),
    Format("reference .csv", _reference_csv, load_references, "text"),
    Format("model .pt", _model_pt, _load_checkpoint(load_model), "pt", checkpoint=True),
    Format("policy .pt", _policy_pt, _load_checkpoint(load_policy), "pt", checkpoint=True),
    Format("limits .yaml", _limits_yaml, GuardLimits.load, "text"),
    Format("limits .json", _limits_json, GuardLimits.load, "text"),
)


# ---------------------------------------------------------------------------------------------- mutation

TOKENS = (
    b"(", b")", b"{", b"}", b"[", b"]", b"'", b'"', b",", b":", b"\\", b"\x00", b"\n", b"\r", b"#", b" ", b"-", b".",
    b"9" * 30, b"-1", b"0", b"1e999", b"-1e308", b"nan", b"inf", b"|O", b"<U9", b"|V8", b">f8", b"<c16", b"True",
    b"None", b"0x", b"\xff\xfe", b"\xc3", b"&a ", b"*a", b"<<: ", b"? ", b"!!int ", b"!!binary ", b"!!python/object:os.system",
    b"2001-13-99", b"[" * 200, b"{" * 200, b"(" * 300, b"'shape': (", b"'descr': ", b"(10000000000, 10000000000)",
    b"\x80\x04\x95", b"\x8e\xff\xff\xff\xff\xff\xff\xff\x7f", b"\x95\xff\xff\xff\xff\xff\xff\xff\x7f", b"B\xff\xff\xff\x7f",
    b"cos\nsystem\n", b"\x8a\xff\xff\xff\x7f", b"h\xff", b"j\xff\xff\xff\x7f", b"]", b"}", b"t", b"R", b"b", b"e", b"s",
    b"PK\x03\x04", b"PK\x01\x02", b"PK\x05\x06", b"!!bool x", b"!!timestamp x", b"!!float x", b"[" * 1100, b"9" * 4400,
)  # fmt: skip
"""Bytes that mean something to one of the parsers: brackets and quotes, huge numbers, dtypes, YAML tags and anchors,
pickle opcodes with huge lengths, zip signatures."""
ZIP_FIELDS = {
    b"PK\x03\x04": ((4, 2), (6, 2), (8, 2), (14, 4), (18, 4), (22, 4), (26, 2), (28, 2)),
    b"PK\x01\x02": ((6, 2), (8, 2), (10, 2), (16, 4), (20, 4), (24, 4), (28, 2), (30, 2), (32, 2), (34, 2), (42, 4)),
    b"PK\x05\x06": ((4, 2), (6, 2), (8, 2), (10, 2), (12, 4), (16, 4), (20, 2)),
    b"PK\x06\x06": ((24, 8), (32, 8), (40, 8), (48, 8)),
    b"PK\x06\x07": ((4, 4), (8, 8), (16, 4)),
}
"""(offset, size) of the fields of a zip's local header, central directory entry, end record and their zip64 forms:
versions, flags, compression method, CRC, sizes, name and extra lengths, entry counts, offsets."""


def header_end(data: bytes, kind: str) -> int:
    """Where a file's header ends: a ``.npy``'s header line, a text file's second line (else 64 bytes).

    Our episode CSV's first line is its ``# meta:`` JSON, the second the column names.
    """
    end = data.find(b"\n", 8) if kind == "npy" else data.find(b"\n", data.find(b"\n") + 1)
    return end + 1 if end > 0 else min(len(data), 64)


def _value(rng: np.random.Generator, original: int, size: int) -> int:
    top = 2 ** (8 * size) - 1
    random = int.from_bytes(rng.bytes(size), "little")
    choices = (0, 1, top, top // 2, original + 1, max(original - 1, 0), original * 2, random)
    return min(int(choices[rng.integers(len(choices))]), top)


def _random_bytes(rng: np.random.Generator) -> bytes:
    if rng.random() < 0.5:
        return TOKENS[rng.integers(len(TOKENS))]
    return rng.integers(0, 256, int(rng.integers(1, 17))).astype(np.uint8).tobytes()


def mutate_bytes(data: bytes, rng: np.random.Generator, header: int) -> tuple[bytes, str]:
    """One byte-level mutation of ``data``, within its first ``header`` bytes for a header edit; (mutant, what)."""
    if not data:
        return _random_bytes(rng), "insertion into an empty file"
    buf = bytearray(data)
    op = ("flip", "bits", "truncate", "insert", "delete", "duplicate", "header", "header", "token")[rng.integers(9)]
    n = len(buf)
    if op == "flip":
        at = rng.integers(0, n, int(rng.integers(1, 9)))
        for i in at:
            buf[int(i)] = int(rng.integers(256))
        return bytes(buf), f"bytes {sorted(int(i) for i in at)} set at random"
    if op == "bits":
        at = int(rng.integers(n))
        buf[at] ^= 1 << int(rng.integers(8))
        return bytes(buf), f"a bit of byte {at} flipped"
    if op == "truncate":
        at = int(rng.integers(min(n, header + 16) if rng.random() < 0.5 else n))
        return bytes(buf[:at]), f"truncated to {at} bytes"
    if op == "insert":
        at, extra = int(rng.integers(n + 1)), _random_bytes(rng)
        return bytes(buf[:at] + extra + buf[at:]), f"{extra[:20]!r} inserted at {at}"
    if op == "delete":
        at = int(rng.integers(n))
        span = int(rng.integers(1, 65))
        return bytes(buf[:at] + buf[at + span :]), f"bytes {at}:{at + span} deleted"
    if op == "duplicate":
        at, to, span = int(rng.integers(n)), int(rng.integers(n + 1)), int(rng.integers(1, 257))
        return bytes(buf[:to] + buf[at : at + span] + buf[to:]), f"bytes {at}:{at + span} copied to {to}"
    if op == "header":
        at = int(rng.integers(max(header, 1)))
        if rng.random() < 0.5:
            buf[at] = int(rng.integers(256))
            return bytes(buf), f"header byte {at} set at random"
        extra = TOKENS[rng.integers(len(TOKENS))]
        return bytes(buf[:at] + extra + buf[at + int(rng.integers(0, 4)) :]), f"header edit: {extra[:20]!r} at {at}"
    at, extra = int(rng.integers(n)), TOKENS[rng.integers(len(TOKENS))]
    return bytes(buf[:at] + extra + buf[at + len(extra) :]), f"{extra[:20]!r} written over byte {at}"


def _rezip(data: bytes, rng: np.random.Generator, inner: str) -> tuple[bytes, str]:
    """Corrupt one member of a zip archive and write the archive back valid (right CRCs and sizes)."""
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        members = [(info, archive.read(info)) for info in archive.infolist()]
    pick = int(rng.integers(len(members)))
    if inner == "pt" and rng.random() < 0.5:  # the pickle most of the time: the part torch parses
        pick = next(i for i, (info, _) in enumerate(members) if info.filename.endswith("data.pkl"))
    name, payload = members[pick][0].filename, members[pick][1]
    mutant, what = mutate_bytes(payload, rng, header_end(payload, "npy") if inner == "npz" else len(payload))
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_STORED) as archive:
        for info, content in members:
            archive.writestr(info.filename, mutant if info.filename == name else content)
    return out.getvalue(), f"member {name}: {what} (archive rewritten valid)"


def _zip_field(data: bytes, rng: np.random.Generator) -> tuple[bytes, str]:
    """Overwrite a field of one of the zip's records (a local header, the central directory, the end record)."""
    found = [(at, sig) for sig in ZIP_FIELDS for at in _positions(data, sig)]
    if not found:
        return mutate_bytes(data, rng, header_end(data, "npy"))
    at, sig = found[int(rng.integers(len(found)))]
    offset, size = ZIP_FIELDS[sig][int(rng.integers(len(ZIP_FIELDS[sig])))]
    start = at + offset
    if start + size > len(data):
        return data[:start], f"truncated inside a {sig!r} record"
    original = int.from_bytes(data[start : start + size], "little")
    value = _value(rng, original, size)
    return data[:start] + value.to_bytes(size, "little") + data[start + size :], (
        f"{sig!r} record at {at}: field +{offset} {original} -> {value}"
    )


def _positions(data: bytes, sig: bytes) -> list[int]:
    positions, at = [], data.find(sig)
    while at >= 0:
        positions.append(at)
        at = data.find(sig, at + 1)
    return positions


def mutant(good: bytes, fmt: Format, seed: int, index: int) -> tuple[bytes, str]:
    """Mutant ``index`` of ``good`` (one to three mutations), the same for the same ``(seed, format, index)``."""
    rng = np.random.default_rng([seed, FORMATS.index(fmt), index])
    data, steps = good, []
    for step in range(int(rng.choice([1, 1, 1, 2, 3]))):
        if fmt.kind in ("npz", "pt") and rng.random() < 0.5:
            # a member is rewritten only in the first step, while the archive is still the good one
            data, what = _rezip(data, rng, fmt.kind) if step == 0 and rng.random() < 0.6 else _zip_field(data, rng)
        else:
            data, what = mutate_bytes(data, rng, header_end(data, fmt.kind))
        steps.append(what)
    return data, "; ".join(steps)


# ------------------------------------------------------------------------------------------------ sweeping


@dataclass
class Outcome:
    """What one format's mutants did: loaded, refused (EfficientTrackError naming the file), or escaped."""

    loaded: int = 0
    refused: int = 0
    escaped: list[tuple[int, str, str]] = field(default_factory=list)
    """(index, how the mutant was made, traceback) of every mutant that escaped."""
    seconds: float = 0.0
    """Time spent making, writing and loading the mutants (not building the good file)."""


def try_load(fmt: Format, path: Path) -> str | None:
    """Load ``path``: None when it loads, ``"refused"`` for an EfficientTrackError naming the file on one line, else
    the traceback of what escaped (or why the EfficientTrackError does not count)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # a mutant that loads may well be odd (RecordWarning, torch's notes)
            warnings.filterwarnings("error", category=RuntimeWarning, module=r"efficienttrack\.")  # as pyproject.toml
            fmt.load(path)
    except EfficientTrackError as exc:
        if str(path) not in str(exc):
            return f"EfficientTrackError without the file's name: {exc}"
        if "\n" in str(exc):
            return f"EfficientTrackError on several lines: {exc}"
        return "refused"
    except Exception:  # what the test is for: anything else escaping the loader
        return traceback.format_exc()
    return None


def sweep(fmt: Format, folder: Path, mutants: int, seed: int = SEED) -> Outcome:
    """Build ``fmt``'s good file in ``folder``, then load ``mutants`` mutants of it, each written over the good file."""
    folder.mkdir(parents=True, exist_ok=True)
    path = fmt.build(folder)
    good = path.read_bytes()
    assert try_load(fmt, path) is None, f"{fmt.name}: the good file does not load"
    outcome = Outcome()
    start = time.perf_counter()
    for index in range(mutants):
        data, what = mutant(good, fmt, seed, index)
        path.write_bytes(data)
        result = try_load(fmt, path)
        if result is None:
            outcome.loaded += 1
        elif result == "refused":
            outcome.refused += 1
        else:
            outcome.escaped.append((index, what, result))
    outcome.seconds = time.perf_counter() - start
    path.write_bytes(good)
    return outcome


@pytest.mark.parametrize("fmt", FORMATS, ids=[fmt.name for fmt in FORMATS])
def test_mutants_load_or_are_refused_naming_the_file(fmt, tmp_path):
    outcome = sweep(fmt, tmp_path, CHECKPOINT_MUTANTS if fmt.checkpoint else MUTANTS)
    if outcome.escaped:
        index, what, text = outcome.escaped[0]
        pytest.fail(
            f"{fmt.name}: {len(outcome.escaped)} mutant(s) escaped (seed {SEED}), indices "
            f"{[i for i, _, _ in outcome.escaped[:20]]}; the first, mutant {index} ({what}):\n{text}"
        )
    assert outcome.refused > 0  # the mutants do damage


# ------------------------------------------------------------------------------- what the sweep found (issue 29)


def _npy(header: bytes, version: int = 1, length: int | None = None) -> bytes:
    length = len(header) if length is None else length
    return b"\x93NUMPY" + bytes([version, 0]) + struct.pack("<H" if version == 1 else "<I", length) + header


def _pickled(opcodes: bytes) -> bytes:
    """An upstream ``.npy`` (a 0-d object array) whose pickle is ``opcodes``."""
    return _npy(b"{'descr': '|O', 'fortran_order': False, 'shape': (), }".ljust(117) + b"\n") + opcodes


def _npz_text_beyond_unicode(good: bytes) -> bytes:
    """The good ``.npz`` with a character code beyond U+10FFFF in its ``meta_json`` (numpy makes a broken str of it)."""
    with zipfile.ZipFile(io.BytesIO(good)) as archive:
        arrays = {info.filename[:-4]: npy_format.read_array(archive.open(info)) for info in archive.infolist()}
    codes = np.frombuffer(arrays["meta_json"].tobytes(), dtype=np.uint32).copy()
    codes[codes == ord("g")] = 0x110000  # the name "good"
    arrays["meta_json"] = codes.view(arrays["meta_json"].dtype).reshape(())
    out = io.BytesIO()
    np.savez(out, **arrays)
    return out.getvalue()


def _checkpoint_pickle(opcodes: bytes) -> Callable[[bytes], bytes]:
    """The good checkpoint with its ``data.pkl`` replaced by ``opcodes`` (a valid zip otherwise)."""

    def replace(good: bytes) -> bytes:
        out = io.BytesIO()
        with zipfile.ZipFile(io.BytesIO(good)) as archive, zipfile.ZipFile(out, "w") as rewritten:
            for info in archive.infolist():
                rewritten.writestr(info.filename, opcodes if info.filename.endswith("data.pkl") else archive.read(info))
        return out.getvalue()

    return replace


FOUND: dict[str, tuple[str, bytes | Callable[[bytes], bytes], str]] = {
    "pt, a persistent id that is no tuple (AssertionError)": (
        "policy .pt",
        _checkpoint_pickle(b"\x80\x02K\x01Q."),  # BININT1 1, BINPERSID, STOP
        "not a plain tensor checkpoint (files must hold data, never code): saved_id must be a tuple",
    ),
    "npz meta_json, a character beyond U+10FFFF (SystemError)": (
        "episode .npz",
        _npz_text_beyond_unicode,
        "field 'meta_json': not readable (ValueError: holds text that is not Unicode (a character code 0x110000))",
    ),
    "csv meta, a 4,400-digit integer (ValueError)": (
        "episode .csv",
        lambda good: good.replace(b'{"name": "good"', b'{"name": "good", "n": 1' + b"0" * 4400, 1),
        "field 'meta' is not valid JSON (ValueError: Exceeds the limit (4300 digits)",
    ),
    "npy header, unterminated (tokenize.TokenError)": (
        "reference .npy",
        _npy(b"{'descr': '<f8', 'fortran_order': False, 'shape': (24, 4), \n"),
        "a damaged header (TokenError",
    ),
    "npy header, bad dtype string (SyntaxError)": (
        "reference .npy",
        _npy(b"{'descr': ',', 'fortran_order': False, 'shape': (24, 4), }\n"),
        "a damaged header (SyntaxError",
    ),
    "npy header, a NUL byte (SystemError from Python 3.12's tokenizer)": (
        "reference .npy",
        _npy(b"{'descr': '<f8', 'fortran_order': False, 'shape': (24, 4), }\0\n"),
        "a damaged header (it holds a NUL byte)",
    ),
    "npy v2 header declaring 4 GiB": ("reference .npy", _npy(b"{}\n", 2, 2**32 - 1), "Header info length 4294967295"),
    "pickle, a frame of 2^62 bytes": ("upstream episode .npy", _pickled(b"\x80\x04\x95" + struct.pack("<Q", 2**62)), ""),
    "pickle, a bytearray of 2^62 bytes": (
        "upstream episode .npy",
        _pickled(b"\x80\x05\x96" + struct.pack("<Q", 2**62)),
        "a bytearray declares 4611686018427387904 bytes",
    ),
    "pickle, bytes of 2^40 bytes": ("upstream episode .npy", _pickled(b"\x80\x04\x8e" + struct.pack("<Q", 2**40)), ""),
    "pickle, bytes of 4 GiB": ("upstream episode .npy", _pickled(b"\x80\x03B" + struct.pack("<I", 2**32 - 1)), ""),
    "upstream csv, a stray quote before 128 KiB (csv.Error)": (
        "upstream episode .csv",
        lambda good: good.replace(b"\n", b'\n"', 1) + good.partition(b"\n")[2] * 100,
        "not a readable CSV (field larger than field limit (131072))",
    ),
    "yaml, an empty !!int (IndexError)": ("limits .yaml", b"!!int\n", "IndexError: string index out of range"),
    "yaml, a month 13 (ValueError)": ("limits .yaml", b"stale_steps: 2001-13-01\n", "ValueError: month must be in 1..12"),
    "yaml, !!int 0x (ValueError)": ("limits .yaml", b"stale_steps: !!int 0x\n", "ValueError: invalid literal"),
    "yaml, !!bool maybe (KeyError)": ("limits .yaml", b"stale_steps: !!bool maybe\n", "KeyError: 'maybe'"),
    "yaml, !!timestamp x (AttributeError)": ("limits .yaml", b"stale_steps: !!timestamp x\n", "AttributeError"),
    "yaml, nested too deeply (RecursionError)": ("limits .yaml", b"stale_steps: " + b"[" * 1200 + b"\n", "nested too deeply"),
    "json, nested too deeply (RecursionError)": ("limits .json", b"[" * 100_000, "nested too deeply"),
    "json, a 5,000-digit integer (ValueError)": ("limits .json", b'{"stale_steps": 1' + b"0" * 5000 + b"}", "(4300 digits)"),
}
"""Files that escaped a loader before issue 29: format, content, a part of the message it now gives."""


@pytest.mark.parametrize("case", sorted(FOUND))
def test_what_escaped_is_refused_naming_the_file(case, tmp_path):
    """Each is refused naming the file; a ``.npy`` never allocates what it declares (at most 8 MiB traced)."""
    name, content, message = FOUND[case]
    fmt = next(fmt for fmt in FORMATS if fmt.name == name)
    path = fmt.build(tmp_path)
    path.write_bytes(content if isinstance(content, bytes) else content(path.read_bytes()))
    traced = path.suffix == ".npy"  # (tracing PyYAML's recursion would take half a minute)
    if traced:
        tracemalloc.start()
    try:
        with pytest.raises(EfficientTrackError, match=re.escape(str(path))) as info:
            fmt.load(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert message in str(info.value)
    assert peak < 8 * 2**20, f"{peak / 2**20:.0f} MiB allocated"


@pytest.mark.parametrize("record, offset, value", [(b"PK\x06\x07", 16, 2), (b"PK\x01\x02", 6, 0x7FFF)])
def test_damaged_zip_records_of_a_checkpoint_are_refused(record, offset, value, tmp_path):
    """zipfile's own errors: a zip64 locator naming several disks (BadZipFile out of ``is_zipfile``), a central directory
    asking for an unknown zip version (NotImplementedError)."""
    path = _policy_pt(tmp_path)
    data = bytearray(path.read_bytes())
    at = data.rfind(record) + offset
    data[at : at + (4 if record == b"PK\x06\x07" else 2)] = value.to_bytes(4 if record == b"PK\x06\x07" else 2, "little")
    path.write_bytes(bytes(data))
    with pytest.raises(EfficientTrackError, match=re.escape(f"{path}: refused to load: a damaged checkpoint archive")):
        load_policy(path)

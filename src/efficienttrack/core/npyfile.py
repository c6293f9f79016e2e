"""Reading ``.npy`` and ``.npz`` files safely: no pickled code, and no array beyond a size bound is ever allocated.

A ``.npy`` header declares its array's dtype and shape, and numpy allocates the whole array before it reads the
data; a ``.npz`` member declares its uncompressed size; a pickle can ask numpy for an array of any shape. A crafted
file of a few hundred bytes can thus expand to gigabytes (a 665 KB ``.npz`` to 640 MB, a 562-byte pickled
``.npy`` to 690 MB). The readers here check what a file declares against :data:`MAX_EXPANDED_BYTES` before
allocating anything, and turn numpy's, zipfile's, zlib's and pickle's exceptions into one
:class:`~efficienttrack.core.errors.EfficientTrackError` naming the file, the field and the problem.
"""

from __future__ import annotations

import io
import math
import os
import pickle
import struct
import sys
import tokenize
import zipfile
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any, ClassVar, cast

import numpy as np
import numpy.lib.format as npy_format

from efficienttrack.core.errors import EfficientTrackError

MAX_EXPANDED_BYTES = 128 * 2**20
"""Most bytes the arrays of one file may expand to (128 MiB). Generous for real data: a record of 500,000 steps
(7 h at 20 Hz) holds five (T, 4) float64 fields and ``t``, 84 MB; the largest XE75 log holds 90 KB, the
largest reference 17 KB, an upstream episode ``.npy`` 185 KB."""

_READ_ERRORS = (OSError, ValueError, EOFError, KeyError, IndexError, TypeError, struct.error, zlib.error, zipfile.BadZipFile)
"""What numpy's header parser, zipfile and zlib raise on a damaged file."""

MAX_HEADER_BYTES = 10_000
"""Longest ``.npy`` header read (numpy's own ``max_header_size``). numpy checks it only after reading the header, and a
version 2 or 3 header declares its length in 4 bytes: a damaged one could make it read (and allocate) up to 4 GiB."""


def _size_text(nbytes: int) -> str:
    return f"{nbytes / 2**20:.1f} MiB" if nbytes >= 2**20 else f"{nbytes} bytes"


def _check_declared(shape: tuple[int, ...], dtype: np.dtype, source: str, budget: int, kinds: str) -> int:
    """Check a declared array before it is allocated; return its size in bytes.

    Args:
        shape: the declared shape.
        dtype: the declared dtype.
        source: file and field, for messages.
        budget: bytes the file may still expand to.
        kinds: the dtype kinds accepted (numpy's ``dtype.kind`` letters, e.g. ``"f"`` for floating point).
    """
    if dtype.kind not in kinds:
        if dtype.hasobject:
            raise EfficientTrackError(f"{source}: holds Python objects (pickled data), refused: files must hold plain arrays")
        expected = {"f": "real floating-point numbers", "U": "a text string"}.get(kinds, f"dtype kind {' or '.join(kinds)}")
        raise EfficientTrackError(f"{source}: has dtype {dtype}, expected {expected}")
    nbytes = math.prod(shape) * dtype.itemsize
    if nbytes > budget:
        raise EfficientTrackError(
            f"{source}: declares a {dtype} array of shape {shape} ({_size_text(nbytes)}), more than the "
            f"{_size_text(MAX_EXPANDED_BYTES)} one file may expand to (efficienttrack.core.npyfile.MAX_EXPANDED_BYTES)"
        )
    return nbytes


def _read_header(f: IO[bytes]) -> tuple[tuple[int, ...], bool, np.dtype]:
    """Read the magic string and header of the ``.npy`` data at ``f``: (shape, fortran_order, dtype).

    The header's declared length is checked against :data:`MAX_HEADER_BYTES` before the header is read; numpy then
    parses it from memory.

    Raises:
        ValueError: an unsupported version, a truncated or overlong header, or one numpy cannot parse.
    """
    version = npy_format.read_magic(f)
    if version == (1, 0):
        length_format, parse = "<H", npy_format.read_array_header_1_0
    elif version in ((2, 0), (3, 0)):
        length_format, parse = "<I", npy_format.read_array_header_2_0
    else:
        raise ValueError(f"unsupported .npy format version {version}")
    length_bytes = f.read(struct.calcsize(length_format))
    if len(length_bytes) != struct.calcsize(length_format):
        raise ValueError("truncated in its header length")
    (length,) = struct.unpack(length_format, length_bytes)
    if length > MAX_HEADER_BYTES:
        raise ValueError(f"Header info length {length} is more than the {MAX_HEADER_BYTES} bytes numpy reads")
    header = f.read(length)
    if len(header) != length:
        raise ValueError(f"truncated in its header ({len(header)} of {length} bytes)")
    if b"\0" in header:  # never in a header numpy writes; Python 3.12's tokenizer fails on it with a SystemError
        raise ValueError("a damaged header (it holds a NUL byte)")
    try:
        return parse(io.BytesIO(length_bytes + header))
    except (tokenize.TokenError, SyntaxError) as exc:  # numpy's header parser (tokenize, ast, np.dtype) lets these out
        problem = exc.args[0] if isinstance(exc, tokenize.TokenError) and exc.args else _first_line(exc)
        raise ValueError(f"a damaged header ({type(exc).__name__}: {problem})") from exc


def _read_data(f: IO[bytes], shape: tuple[int, ...], fortran: bool, dtype: np.dtype, nbytes: int) -> np.ndarray:
    """Read exactly ``nbytes`` of array data after the header and nothing more; a writable array."""
    data = f.read(nbytes + 1)
    if len(data) != nbytes:
        raise ValueError(f"holds {len(data)}{'+' if len(data) > nbytes else ''} bytes of data, its header declares {nbytes}")
    _check_text(data, dtype)
    flat = np.frombuffer(data, dtype=dtype)
    return (flat.reshape(shape[::-1]).T if fortran else flat.reshape(shape)).copy()


def _check_text(data: bytes, dtype: np.dtype) -> None:
    """Refuse the data of a text array (dtype kind ``U``, UCS-4) that holds a code point beyond U+10FFFF.

    numpy makes a Python string of such data without a check, and the string then fails in unrelated places (a
    ``SystemError`` from iterating over it).
    """
    if dtype.kind == "U" and data:
        codes = np.frombuffer(data, dtype=np.dtype(np.uint32).newbyteorder(dtype.byteorder))
        if codes.size and int(codes.max()) > sys.maxunicode:
            raise ValueError(f"holds text that is not Unicode (a character code {int(codes.max()):#x})")


def read_npy(path: str | Path, kinds: str = "f") -> np.ndarray:
    """Read a plain ``.npy`` array, its declared size and dtype checked before anything is allocated.

    Args:
        path: the file.
        kinds: dtype kinds accepted (``"f"``: real floating point; bool, complex, strings and objects are refused).

    Returns:
        The array.

    Raises:
        EfficientTrackError: empty, truncated or damaged file, a refused dtype, or more than :data:`MAX_EXPANDED_BYTES`.
    """
    path = Path(path)
    try:
        with path.open("rb") as f:
            if not f.peek(1):
                raise EfficientTrackError(f"{path}: empty file (0 bytes), not a .npy array")
            shape, fortran, dtype = _read_header(f)
            nbytes = _check_declared(shape, dtype, str(path), MAX_EXPANDED_BYTES, kinds)
            return _read_data(f, shape, fortran, dtype, nbytes)
    except EfficientTrackError:
        raise
    except _READ_ERRORS as exc:
        raise EfficientTrackError(f"{path}: not a readable .npy array ({_first_line(exc)})") from exc


def read_npz(path: str | Path, kinds: dict[str, str] | None = None, default_kinds: str = "f") -> dict[str, np.ndarray]:
    """Read every array of an ``.npz`` (as written by ``np.savez``), never allocating more than :data:`MAX_EXPANDED_BYTES`.

    The members' declared uncompressed sizes are checked first, then each member's ``.npy`` header, before its data
    is read.

    Args:
        path: the file.
        kinds: dtype kinds accepted per field (member name without ``.npy``), e.g. ``{"meta_json": "U"}``.
        default_kinds: dtype kinds accepted for the other fields (``"f"``: real floating point).

    Returns:
        Field name → array.

    Raises:
        EfficientTrackError: naming the file and the field: not a zip file, a damaged member (zlib, CRC), a refused
            dtype, a truncated array, or arrays expanding to more than :data:`MAX_EXPANDED_BYTES`.
    """
    path = Path(path)
    kinds = kinds or {}
    source = str(path)
    try:
        if path.stat().st_size == 0:
            raise EfficientTrackError(f"{path}: not a readable .npz archive (empty file, 0 bytes)")
        with zipfile.ZipFile(path) as archive:
            members = archive.infolist()
            declared = sum(member.file_size for member in members)
            if declared > MAX_EXPANDED_BYTES:
                raise EfficientTrackError(
                    f"{path}: its members expand to {_size_text(declared)}, more than the {_size_text(MAX_EXPANDED_BYTES)} "
                    "one file may expand to (efficienttrack.core.npyfile.MAX_EXPANDED_BYTES)"
                )
            arrays: dict[str, np.ndarray] = {}
            for member in members:
                field = member.filename.removesuffix(".npy")
                source = f"{path}: field '{field}'"
                if not member.filename.endswith(".npy"):
                    raise EfficientTrackError(f"{path}: member '{member.filename}' is not a .npy array")
                with archive.open(member) as f:
                    shape, fortran, dtype = _read_header(f)
                    nbytes = _check_declared(shape, dtype, source, member.file_size, kinds.get(field, default_kinds))
                    arrays[field] = _read_data(f, shape, fortran, dtype, nbytes)
            return arrays
    except EfficientTrackError:
        raise
    except zipfile.BadZipFile as exc:
        if source == str(path):
            raise EfficientTrackError(
                f"{path}: not a readable .npz archive (a zip of .npy arrays): {_first_line(exc)}"
            ) from exc
        raise EfficientTrackError(f"{source}: damaged ({_first_line(exc)})") from exc
    except zlib.error as exc:
        raise EfficientTrackError(f"{source}: damaged compressed data (zlib: {_first_line(exc)})") from exc
    except (*_READ_ERRORS, NotImplementedError, RuntimeError) as exc:  # unsupported compression, encrypted member
        raise EfficientTrackError(f"{source}: not readable ({type(exc).__name__}: {_first_line(exc)})") from exc


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


# ------------------------------------------------------------------------------------- pickled object arrays


_RECONSTRUCT = cast(Callable[..., np.ndarray], np.ndarray.__reduce__(np.empty(0))[0])
"""numpy's array reconstructor (``numpy._core.multiarray._reconstruct``, ``numpy.core`` before numpy 2)."""
_NDARRAY = object()
"""What the name ``numpy.ndarray`` unpickles to: a marker only :func:`_RECONSTRUCT` accepts, never the callable class."""


class _NumpyOnlyUnpickler(pickle._Unpickler):
    """Unpickler that builds numpy arrays, dtypes and plain containers, bounded in size; it refuses every other global.

    The pure-Python unpickler, so that ``BUILD`` (``__setstate__``) can be checked: an array's state must match its
    declared shape exactly (numpy does not check an object array's list length and reads past it), and a dtype's may
    not add fields or sub-arrays.
    """

    dispatch: ClassVar[dict[int, Callable[[Any], None]]] = dict(pickle._Unpickler.dispatch)
    stack: list[Any]
    """The pure-Python unpickler's value stack (undocumented, so typeshed leaves it out)."""
    read: Callable[[int], bytes]
    """Reads the next bytes of the pickle, within the current frame (set by ``load``; undocumented too)."""
    append: Callable[[Any], None]
    """Pushes a value on the stack (set by ``load``; undocumented too)."""

    def __init__(self, data: bytes, source: Path) -> None:
        super().__init__(io.BytesIO(data))
        self.source = source
        self.size = len(data)
        self.budget = MAX_EXPANDED_BYTES

    def _refuse(self, problem: str) -> EfficientTrackError:
        return EfficientTrackError(f"{self.source}: {problem} (the file is corrupt or malicious)")

    def find_class(self, module: str, name: str) -> Any:
        """Return a checked stand-in for numpy's array or dtype constructor; refuse anything else."""
        if module in ("numpy.core.multiarray", "numpy._core.multiarray") and name == "_reconstruct":
            return self._reconstruct
        if (module, name) == ("numpy", "ndarray"):
            return _NDARRAY
        if (module, name) == ("numpy", "dtype"):
            return self._dtype
        raise self._refuse(f"refused to unpickle global '{module}.{name}': only numpy arrays may be stored")

    def _reconstruct(self, subtype: object, shape: object, dtype: object) -> np.ndarray:
        if subtype is not _NDARRAY or not isinstance(shape, tuple) or shape != (0,):
            raise self._refuse("refused an array reconstruction other than numpy's own (an empty ndarray to fill)")
        return _RECONSTRUCT(np.ndarray, shape, dtype)

    def _dtype(self, spec: object, *args: Any) -> np.dtype:
        if not isinstance(spec, str):
            raise self._refuse(f"refused a structured dtype {spec!r}")
        return np.dtype(spec, *args)

    def load_build(self) -> None:
        """``BUILD``: set an array's or a dtype's state after checking it; refuse any other object."""
        state = self.stack.pop()
        inst = self.stack[-1]
        if isinstance(inst, np.ndarray):
            self._check_array_state(state)
        elif not (isinstance(inst, np.dtype) and _plain_dtype_state(state, inst)):
            raise self._refuse(f"refused to set the state of a {type(inst).__name__} (only plain arrays and dtypes)")
        inst.__setstate__(state)

    dispatch[pickle.BUILD[0]] = load_build

    def load_bytearray8(self) -> None:
        """``BYTEARRAY8``: refuse a declared length beyond the pickle's own size before the bytearray is allocated.

        The one opcode that allocates what its length declares before reading (the others read from memory, see
        :func:`read_pickled_npy`, and find the data short).
        """
        (length,) = struct.unpack("<Q", self.read(8))
        if length > self.size:
            raise self._refuse(f"a bytearray declares {length} bytes, more than the {self.size}-byte pickle holds")
        data = bytearray(self.read(length))
        if len(data) != length:
            raise pickle.UnpicklingError("pickle data was truncated")
        self.append(data)

    dispatch[pickle.BYTEARRAY8[0]] = load_bytearray8

    def _check_array_state(self, state: object) -> None:
        """An array's state ``(1, shape, dtype, fortran, data)`` must declare an allowed size and hold exactly that data."""
        if not (
            isinstance(state, tuple) and len(state) == 5 and isinstance(state[1], tuple) and isinstance(state[2], np.dtype)
        ):
            raise self._refuse("an array's pickled state is not (version, shape, dtype, fortran_order, data)")
        _, shape, dtype, _, data = state
        if not all(isinstance(n, int) and n >= 0 for n in shape):
            raise self._refuse(f"an array declares an invalid shape {shape}")
        self.budget -= _check_declared(shape, dtype, str(self.source), self.budget, "biufcUSO")
        count = math.prod(shape)
        if dtype.hasobject:
            exact = isinstance(data, list) and len(data) == count
        else:
            exact = isinstance(data, bytes) and len(data) == count * dtype.itemsize
        if not exact:
            raise self._refuse(f"an array of shape {shape} and dtype {dtype} holds data of another size")
        if isinstance(data, bytes):
            _check_text(data, dtype)


def _plain_dtype_state(state: object, dtype: np.dtype) -> bool:
    """Whether a pickled dtype state ``(version, byteorder, subarray, names, fields, elsize, alignment, flags)`` is plain.

    No sub-array, no fields, and the element size and alignment the dtype already has.
    """
    return (
        isinstance(state, tuple)
        and len(state) == 8
        and state[2:5] == (None, None, None)
        and state[5] in (-1, dtype.itemsize)
        and state[6] in (-1, dtype.alignment)
    )


def read_pickled_npy(path: str | Path, what: str) -> Any:
    """Read a ``.npy`` holding one pickled 0-d object array (``np.save`` of a Python object) without running any code.

    Its pickle may only build numpy arrays, dtypes and plain containers (lists, dicts, numbers, strings); the arrays
    are checked against :data:`MAX_EXPANDED_BYTES` (all of them together) before they are allocated.

    Args:
        path: the file.
        what: what the file should hold, for the message when it holds a plain array instead.

    Returns:
        The object the 0-d array holds.

    Raises:
        EfficientTrackError: a header other than a 0-d object array, a refused global or state, or a damaged pickle.
    """
    path = Path(path)
    try:
        with path.open("rb") as f:
            if not f.peek(1):
                raise EfficientTrackError(f"{path}: empty file (0 bytes), not a .npy array")
            shape, _, dtype = _read_header(f)
            if dtype != np.dtype(object) or shape != ():
                raise EfficientTrackError(f"{path}: holds a {dtype} array of shape {shape}, not {what}")
            # The pickle is unpickled from memory: an opcode that declares a length (a frame, bytes, a string) then
            # reads no more than the file holds, where reading the file would allocate the declared length first.
            size = os.fstat(f.fileno()).st_size - f.tell()
            if size > MAX_EXPANDED_BYTES:
                raise EfficientTrackError(
                    f"{path}: its pickle holds {_size_text(size)}, more than the {_size_text(MAX_EXPANDED_BYTES)} one "
                    "file may expand to (efficienttrack.core.npyfile.MAX_EXPANDED_BYTES)"
                )
            data = f.read(size)
        content = _NumpyOnlyUnpickler(data, path).load()
    except EfficientTrackError:
        raise
    except (*_READ_ERRORS, AttributeError, OverflowError, pickle.UnpicklingError) as exc:
        raise EfficientTrackError(f"{path}: not a readable pickled .npy ({type(exc).__name__}: {_first_line(exc)})") from exc
    if not (isinstance(content, np.ndarray) and content.dtype == object and content.shape == ()):
        raise EfficientTrackError(f"{path}: the pickled object is a {type(content).__name__}, not a 0-d object array")
    return content.item()

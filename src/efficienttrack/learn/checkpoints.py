"""Checkpoint files of the networks: save and load (tensors only, never code), warm starts, and their checks.

A checkpoint is a ``state_dict`` written with ``torch.save`` (``model.pt``) and its config as JSON beside it
(``model.json``); :func:`load_tensors` reads any such file with ``weights_only=True`` and bounds what an archive may
expand to, so a file from elsewhere can neither run code nor exhaust memory.
"""

from __future__ import annotations

import hashlib
import json
import pickle
import struct
import warnings
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import torch
from torch import nn

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import atomic_write, write_json
from efficienttrack.core.npyfile import MAX_EXPANDED_BYTES
from efficienttrack.core.provenance import provenance
from efficienttrack.core.settings import plain_form
from efficienttrack.learn.nets import resolve_device

NetworkT = TypeVar("NetworkT", bound=nn.Module)


def warm_start(network: NetworkT, init: nn.Module, what: str) -> NetworkT:
    """Load ``init``'s weights and feature scaling into ``network`` (same config sizes): a round's warm start.

    The scaling buffers come along with the weights they were trained with; a warm-started network is not
    rescaled on the new data.

    Args:
        network: the freshly built network (its config decides the sizes).
        init: the trained network to start from.
        what: how to name ``init`` in errors (e.g. ``--init-model``).

    Returns:
        ``network``, holding ``init``'s state.

    Raises:
        EfficientTrackError: ``init`` has other sizes than ``network``'s config.
    """
    try:
        network.load_state_dict(init.state_dict())
    except RuntimeError as exc:
        raise EfficientTrackError(f"{what}: its sizes do not match the config trained ({str(exc).splitlines()[0]})") from exc
    return network


def check_checkpoint_path(path: str | Path, option: str = "--out") -> Path:
    """Refuse, before any training, a checkpoint path that does not end in ``.pt``.

    The files that go with a checkpoint are named from it by suffix (``model.pt``: config ``model.json``, training
    state ``model.state.pt``, logs ``model.logs/``); another suffix could make two of them one file (``--out m.json``
    would be written over by its own config) or hide what the file is.

    Args:
        path: the checkpoint to write.
        option: the command-line option naming it, for messages.

    Returns:
        ``path`` as a Path.
    """
    path = Path(path)
    if path.suffix != ".pt":
        clash = " (the checkpoint and its config would be one file)" if path.suffix == ".json" else ""
        raise EfficientTrackError(
            f"{option} {path}: a checkpoint must end in .pt{clash}; its config is written beside it as "
            f"{path.with_suffix('.json').name}, e.g. {option} {path.with_suffix('.pt')}"
        )
    return path


def config_path(path: str | Path) -> Path:
    """The JSON config that lies next to checkpoint ``path`` (``model.pt`` → ``model.json``)."""
    path = Path(path)
    if path.suffix == ".json":
        raise EfficientTrackError(f"{path}: a checkpoint path must not end in .json (its config is written there)")
    return path.with_suffix(".json")


def record_evaluation(path: str | Path, evaluation: dict[str, Any]) -> None:
    """Keep what the checkpoint at ``path`` was last measured with in its own JSON config (``"evaluation"``).

    The verdict then travels with the checkpoint: a copy holds it (a checkpoint is its ``.pt`` with its ``.json``), and
    an export carries it into its contract, so ``deploy --arm`` finds it without the run folder that measured it.

    Args:
        path: the checkpoint (``policy.pt``); its JSON config must lie next to it.
        evaluation: JSON-serializable facts (``mae_deg``, ``pd_mae_deg``, ``worse_than_pd``, the references, the system).
    """
    cfg_file = config_path(path)
    try:
        meta = json.loads(cfg_file.read_text())
        write_json(cfg_file, {**meta, "evaluation": evaluation})
    except (OSError, ValueError) as exc:
        raise EfficientTrackError(f"{cfg_file}: cannot record the evaluation in the checkpoint's config ({exc})") from exc


def save_checkpoint(module: nn.Module, kind: str, config: Any, path: str | Path, fingerprint: str | None = None) -> Path:
    """Write ``module``'s state_dict (``torch.save``) and its config as JSON next to it, both atomically.

    The JSON holds ``kind``, ``config``, ``weights_sha256``, ``training_fingerprint`` and ``provenance``
    (:func:`~efficienttrack.core.provenance.provenance`, with the device the module lies on). Checkpoints written before
    ``training_fingerprint`` existed load all the same.

    Args:
        module: the network (its buffers, e.g. feature scaling, are part of the state_dict).
        kind: what it is (``"closed_loop_model"``, ``"adjustment_policy"``), checked on load.
        config: the frozen config dataclass it was built from.
        path: checkpoint file, e.g. ``model.pt``; the config goes to ``model.json``.
        fingerprint: what the network was trained from (:func:`fingerprint`: the records, the seed, the networks it
            trained through or started from), the same digest its training state holds; None when not known.

    Returns:
        The checkpoint path.
    """
    path = Path(path)
    check_finite(module, f"{path}: {kind} not saved")
    tensors = module.state_dict()
    state = {name: tensor.detach().cpu() for name, tensor in tensors.items()}
    atomic_write(path, lambda f: torch.save(state, f))
    device = next(iter(tensors.values())).device if tensors else None
    meta = {
        "kind": kind,
        "config": plain_form(config),
        "weights_sha256": _file_sha256(path),
        "training_fingerprint": fingerprint,
        "provenance": provenance(device),
    }
    write_json(config_path(path), meta)
    return path


def check_finite(module: nn.Module, what: str) -> None:
    """Refuse a network whose weights or buffers hold NaN/inf (a diverged training), before it is saved or resumed.

    Args:
        module: the network.
        what: the start of the message: the file and what is refused (``"model.pt: not saved"``).

    Raises:
        EfficientTrackError: naming the first non-finite tensors.
    """
    bad = [name for name, tensor in module.state_dict().items() if tensor.is_floating_point() and not tensor.isfinite().all()]
    if bad:
        raise EfficientTrackError(
            f"{what}: the weights hold NaN/inf values ({', '.join(bad[:3])}), the training diverged (check the data for "
            "absurd values, lower the learning rate)"
        )


def _file_sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def load_checkpoint(
    path: str | Path,
    kind: str,
    config: Callable[[dict, str], Any],
    network: Callable[[Any], NetworkT],
    device: str | torch.device,
) -> NetworkT:
    """Read a checkpoint written by :func:`save_checkpoint`: tensors only (``weights_only=True``), never code.

    Args:
        path: the checkpoint file; its JSON config must lie next to it.
        kind: the expected kind.
        config: reads the JSON config, field by field, naming its source in errors (a config class's ``from_stored``).
        network: builds the network from its config (the module class).
        device: where to put the network (``"auto"``, ``"cpu"``, ``"cuda"``, ``"cuda:N"`` or a torch device).

    Returns:
        The network with the saved weights, in eval mode on ``device``.

    Raises:
        EfficientTrackError: missing files, a config of another kind or with bad fields, a file that is not a plain
            state_dict (e.g. a pickle holding code), or weights that do not match the config.
    """
    path = Path(path)
    cfg_file = config_path(path)
    if not path.is_file():
        raise EfficientTrackError(f"{path}: no such checkpoint file")
    if not cfg_file.is_file():
        raise EfficientTrackError(f"{path}: its config {cfg_file} is missing (a checkpoint is the .pt file plus its .json)")
    try:
        meta = json.loads(cfg_file.read_text())
    except (OSError, ValueError) as exc:  # ValueError: bad JSON, or not text (UnicodeDecodeError)
        raise EfficientTrackError(f"{cfg_file}: not a readable JSON config ({exc})") from exc
    if not isinstance(meta, dict) or meta.get("kind") != kind or not isinstance(meta.get("config"), dict):
        found = meta.get("kind") if isinstance(meta, dict) else type(meta).__name__
        raise EfficientTrackError(f"{cfg_file}: expected a '{kind}' config, found '{found}'")
    state = load_tensors(path)
    if not all(isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in state.items()):
        raise EfficientTrackError(f"{path}: not a state_dict (expected a dict of named tensors)")
    if meta.get("weights_sha256") not in (None, _file_sha256(path)):
        raise EfficientTrackError(f"{cfg_file}: written for other weights than {path} (an interrupted save?); save both again")
    bad = [name for name, tensor in state.items() if tensor.is_floating_point() and not torch.isfinite(tensor).all()]
    if bad:
        raise EfficientTrackError(
            f"{path}: weights hold NaN/inf values ({', '.join(bad[:3])}); the training diverged, retrain"
        )
    module = network(config(meta["config"], f"{path} config"))
    try:
        module.load_state_dict(state)
    except RuntimeError as exc:
        raise EfficientTrackError(f"{path}: weights do not match its config ({str(exc).splitlines()[0]})") from exc
    return module.to(resolve_device(device)).eval()


CHECKPOINT_READ_ERRORS = (
    pickle.UnpicklingError, RuntimeError, EOFError, OSError, ValueError, AttributeError, IndexError, KeyError, TypeError,
    OverflowError, struct.error, AssertionError,
)  # fmt: skip
"""What ``torch.load(weights_only=True)`` raises on a file that is not a checkpoint (random bytes give all of these;
a damaged persistent id in its pickle gives AssertionError, "saved_id must be a tuple")."""


def _starts_as_zip(path: str | Path) -> bool:
    """Whether the file starts with a zip's local file header: what makes ``torch.load`` read it as an archive."""
    with open(path, "rb") as f:
        return f.read(4) == b"PK\x03\x04"


def load_tensors(path: str | Path) -> dict[str, Any]:
    """``torch.load(path, weights_only=True)`` on CPU, with a clear error for anything but tensors and plain containers.

    A checkpoint is a zip archive, and ``torch.load`` allocates every member's declared size, also of a compressed
    member (``torch.save`` stores them uncompressed): a crafted file of a few KB could ask for gigabytes. The members
    may together declare at most the file's own size or :data:`~efficienttrack.core.npyfile.MAX_EXPANDED_BYTES`, whichever
    is larger, before anything is loaded.

    Args:
        path: a file written by ``torch.save``.

    Returns:
        The loaded dict.
    """
    size = Path(path).stat().st_size if Path(path).is_file() else None
    if size == 0:
        raise EfficientTrackError(f"{path}: empty file (0 bytes), not a checkpoint")
    declared = 0
    try:
        # torch reads a file as a zip archive when it starts with a zip's local header, whatever zipfile thinks of it
        if size is not None and (_starts_as_zip(path) or zipfile.is_zipfile(path)):
            with zipfile.ZipFile(path) as archive:
                declared = sum(member.file_size for member in archive.infolist())
    # is_zipfile lets BadZipFile out (a zip64 end record naming several disks); ZipFile raises NotImplementedError for
    # a zip version it does not know and ValueError (UnicodeDecodeError) for a member name that is not UTF-8
    except (zipfile.BadZipFile, NotImplementedError, OSError, ValueError, EOFError, struct.error) as exc:
        raise EfficientTrackError(f"{path}: refused to load: a damaged checkpoint archive ({exc})") from exc
    if size is not None and declared > max(size, MAX_EXPANDED_BYTES):
        raise EfficientTrackError(
            f"{path}: refused to load: its {size}-byte archive expands to {declared / 2**20:.1f} MiB, more than the "
            f"file itself or the {MAX_EXPANDED_BYTES / 2**20:.0f} MiB a compressed checkpoint may expand to "
            "(efficienttrack.core.npyfile.MAX_EXPANDED_BYTES)"
        )
    try:
        with warnings.catch_warnings():  # a damaged file can make torch warn about its pickle protocol before failing
            warnings.simplefilter("ignore", UserWarning)
            data = torch.load(path, map_location="cpu", weights_only=True)
    except CHECKPOINT_READ_ERRORS as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise EfficientTrackError(
            f"{path}: refused to load: not a plain tensor checkpoint (files must hold data, never code): {first}"
        ) from exc
    if not isinstance(data, dict):
        raise EfficientTrackError(f"{path}: holds a {type(data).__name__}, expected a dict of tensors")
    return data

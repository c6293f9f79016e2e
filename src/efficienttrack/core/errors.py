"""The one exception type for problems the user can fix (bad files, bad specs, bad options).

The CLI prints these as a one-line message and exits non-zero; anything else is a bug and
keeps its traceback.
"""

from __future__ import annotations

EXTRAS = {
    "torch": "train",
    "tensorboard": "train",
    "onnx": "train",
    "matplotlib": "train",
    "scipy": "train",
    "gymnasium": "study",
    "stable_baselines3": "study",
    "ray": "study",
    "rosbags": "ros",
}
"""The extra (pyproject.toml) that installs each library the core install leaves out and the package imports."""


class EfficientTrackError(Exception):
    """A user-facing error: the message names the file, field or option and the problem."""


class MissingExtraError(EfficientTrackError, ModuleNotFoundError):
    """A library of an extra is not installed: the message names the extra that installs it (still an ImportError)."""


def missing_extra(exc: ModuleNotFoundError, what: str) -> MissingExtraError | None:
    """The error to raise for ``exc`` when the missing module is a library an extra installs.

    Args:
        exc: the import's error.
        what: what needs the library, opening the message (``this command``, ``efficienttrack.train_model``).

    Returns:
        ``<what> needs <library>, which is not installed: pip install 'efficienttrack[<extra>]'`` (and the same from a
        clone, there being no release on PyPI yet), or None when the
        missing module is no extra's (a broken install, or a bug: keep the original error).
    """
    library = (exc.name or "").split(".")[0]
    if library not in EXTRAS:
        return None
    extra = EXTRAS[library]
    error = MissingExtraError(
        f"{what} needs {library}, which is not installed: pip install 'efficienttrack[{extra}]' (in a clone of the "
        f"repository: pip install '.[{extra}]')"
    )
    error.name = exc.name
    return error

"""The one exception type for problems the user can fix (bad files, bad specs, bad options).

The CLI prints these as a one-line message and exits non-zero; anything else is a bug and
keeps its traceback.
"""


class EfficientTrackError(Exception):
    """A user-facing error: the message names the file, field or option and the problem."""

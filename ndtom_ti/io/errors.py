"""Exceptions of the recording-reading layer."""

from __future__ import annotations


class RecordingError(Exception):
    """A problem with an input recording, pose file or message.

    The message says what was wrong and what to do about it; callers (the CLI)
    print it as is.
    """


class TransformTimeError(RecordingError):
    """A transform exists between two frames but not at the requested time.

    Kept separate from structural TF problems so that a scan stream can skip the
    cloud (and count it) instead of aborting.
    """

"""The error raised for a bad debris/satellite object or observer: names the key and what was expected."""

from __future__ import annotations

from ..errors import SceneError


class ObjectError(SceneError):
    """A user error in an ``[[objects]]`` entry, an observer, or a TLE.

    ``key`` is the dotted scene key (``objects[2].tle``, ``observer.lat_deg``); the one-line message is what
    the CLI prints (see :class:`detector.errors.DetectorError`).
    """

"""The error of a bad scene: one line naming the file, the key and what was expected (exit status 2)."""

from __future__ import annotations

from detector import DetectorError


class SceneError(DetectorError):
    """A user mistake in a scene file, a ``--set`` override, or a file the scene names."""

"""newtsim's observation: what the telescope looks at and how it becomes light on the sensor.

The observation model lives here (``scene`` and ``errors``, ``sky/``, ``objects/``, ``projection``,
``photometry``, ``straylight``, ``image/``); the application that uses it (render, batch, compare/diagnose,
the command line, quick-looks) lives in ``scenes.app``, and nothing here imports it.
``scenes`` uses ``detector`` (the sensor) and ``optics`` (the telescope); neither knows of ``scenes``.
"""

__all__ = ["Scene", "SceneError", "load_scene"]


def __getattr__(name):
    """``scenes.Scene`` etc. on first use: importing ``scenes.app.cli`` loads nothing heavy before the
    command line has installed its signal handlers (an interrupt while importing is one line)."""
    if name == "SceneError":
        from .errors import SceneError

        return SceneError
    if name in ("Scene", "load_scene"):
        from . import scene

        return getattr(scene, name)
    raise AttributeError(f"module 'scenes' has no attribute {name!r}")

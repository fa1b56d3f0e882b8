"""newtsim's observation: what the telescope looks at and how it becomes light on the sensor.

The observation model lives here (``scene`` and ``errors``, ``sky/``, ``objects/``, ``projection``,
``photometry``, ``straylight``, ``image/``); the application that uses it (render, batch, compare/diagnose,
the command line, quick-looks) lives in ``scenes.app``, and nothing here imports it.
``scenes`` uses ``detector`` (the sensor) and ``optics`` (the telescope); neither knows of ``scenes``.
"""

from .errors import SceneError
from .scene import Scene, load_scene

__all__ = ["Scene", "SceneError", "load_scene"]

"""newtsim's observation layer: scene files, sky, projection, image formation, the pipeline and the CLI.

``scenes`` uses ``detector`` (the sensor) and ``optics`` (the telescope); neither knows of ``scenes``.
"""

from .render import render
from .scene import Scene, SceneError, load_scene

__all__ = ["Scene", "SceneError", "load_scene", "render"]

"""newtsim's sensor model: expected electrons in, a CCD/CMOS frame in ADU out.

>>> from detector import make_sensor, Detector, build_effects
>>> s = make_sensor("ml11002", {"width": 256, "height": 256})
>>> det = Detector(s, build_effects({"prnu": {"sigma": 0.01}}, s))
>>> frame = det.expose(100.0, exptime_s=10.0, frame_seed=1)

``detector`` imports neither ``optics`` nor ``scenes`` and works without Mitsuba.
"""

from .chain import Detector
from .effects import Effect, EffectParams, Stage, Tile, build_effects, register_effect, registry
from .errors import DetectorError
from .presets import PRESETS, SOURCES
from .sensor import SensorConfig, make_sensor

__all__ = ["Detector", "DetectorError", "Effect", "EffectParams", "PRESETS", "SOURCES", "SensorConfig",
           "Stage", "Tile", "build_effects", "make_sensor", "register_effect", "registry"]

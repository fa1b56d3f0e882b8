"""The effect plug-in interface: stages, tiles, the ``Effect`` base class and the registry.

An effect is a pure physics function (in its own module, testable on plain arrays) plus a thin adapter
class registered here. The adapter declares

* ``name``: the catalogue name used in scene files (``[effects.NAME]``);
* ``stages``: where in the chain it acts (see :class:`Stage`);
* ``Params``: a pydantic model whose fields carry defaults, bounds and units (``json_schema_extra``);
* ``apply(stage, tile, data)``: works in place on the tile's array for that stage;
* optionally ``setup()`` (draw the hardware pattern once, from the hardware seed) and ``truth()``
  (tables written to the FITS file so every frame can be explained).

Users add their own effects without editing the package, either with ``@register_effect`` in their
code or through the ``newtsim.effects`` entry-point group of their own package.
"""

from __future__ import annotations

import enum
import os
import re
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict

from ..errors import DetectorError
from ..rng import BAND_ROWS, generator
from ..sensor import SensorConfig


class Stage(enum.IntEnum):
    """Where an effect acts, in chain order, with the unit of the array it receives."""

    FIELD = 0  #: once per frame, on the whole expected photo-electron image [e-] (blooming)
    RESPONSE = 1  #: multiplies the expected photo-electrons [e-] (PRNU, dead pixels, vignetting-like)
    DARK = 2  #: adds to the expected (mean) signal before the shot-noise draw [e-] (DSNU, hot pixels, glow)
    CHARGE = 3  #: acts on the drawn charge, before the full-well clip [e-] (cosmic rays)
    READ = 4  #: acts on the clipped charge at read-out, before read noise [e-] (nonlinearity, kTC, rows)
    ADU = 5  #: acts on the converted signal, bias not yet added [ADU] (gain regions, crosstalk, bias shape)
    DIGITAL = 6  #: acts on the quantised frame before binning [ADU] (stuck pixels)
    #: couples pixels after the full-well clip, before binning and READ [e-] (brighter-fatter, CTI, IPC). Its
    #: number is last so the older stages keep theirs; in the chain it runs between CHARGE and READ. The
    #: effect sees the tile's rows plus ``halo_rows`` rows of the neighbouring tiles above and below
    #: (``halo_rows = None``: the whole read-out window) and returns a new array of the same shape.
    COUPLING = 7


class EffectParams(BaseModel):
    """Base of every effect's parameter model: unknown keys are errors."""

    model_config = ConfigDict(extra="forbid")


@dataclass
class Tile:
    """A band of rows of the read-out window, processed independently of the others.

    Coordinates are absolute sensor pixels: rows ``y0:y1`` and columns ``x0:x1``. After charge-domain
    binning (CCD) the arrays shrink by ``bin`` in both axes; :meth:`pixel_centres` follows.
    """

    sensor: SensorConfig
    index: int
    y0: int
    y1: int
    x0: int
    x1: int
    exptime_s: float
    frame_seed: int
    bin: int = 1
    #: per-frame state of each effect (``Effect.prepare_frame``), keyed by effect name, shared by all tiles
    state: dict = field(default_factory=dict, repr=False)
    _cache: dict = field(default_factory=dict, repr=False)

    @property
    def shape(self) -> tuple[int, int]:
        return ((self.y1 - self.y0) // self.bin, (self.x1 - self.x0) // self.bin)

    def rng(self, name: str) -> np.random.Generator:
        """The frame-seed stream of ``name`` for this tile (new noise every frame)."""
        return generator(self.frame_seed, name, self.index)

    def pixel_centres(self) -> tuple[np.ndarray, np.ndarray]:
        """Sensor coordinates (y, x) of the centres of the current (possibly binned) pixels, 1-D each."""
        b = self.bin
        ys = self.y0 + b * np.arange(self.shape[0]) + (b - 1) / 2.0
        xs = self.x0 + b * np.arange(self.shape[1]) + (b - 1) / 2.0
        return ys, xs

    def row_start_s(self) -> np.ndarray:
        """Exposure start time of each current row relative to the first read-out row (thesis eq. 10)."""
        ys, _ = self.pixel_centres()
        return (ys - (self.sensor.roi_y0 + (self.bin - 1) / 2.0)) * self.sensor.row_time_s

    def release(self) -> None:
        """Drop the hardware maps cached for this tile (the chain calls it when the tile is done)."""
        self._cache.clear()

    def hardware_map(self, name: str, draw: Callable[[np.random.Generator, tuple[int, int]], np.ndarray]
                     ) -> np.ndarray:
        """A dense fixed-pattern map for this tile, drawn from the hardware seed.

        ``draw(rng, shape)`` is called once per random-number band of the *full* sensor width, so the map
        of a pixel does not depend on the region of interest, the tile size or the thread count.
        """
        key = ("hw", name)
        if key in self._cache:
            return self._cache[key]
        s = self.sensor
        bands = []
        b0, b1 = self.y0 // BAND_ROWS, (self.y1 - 1) // BAND_ROWS
        for b in range(b0, b1 + 1):
            rows = min(BAND_ROWS, s.sensor_height_px - b * BAND_ROWS)
            bands.append(np.asarray(draw(generator(s.hardware_seed, name, b), (rows, s.sensor_width_px))))
        full = bands[0] if len(bands) == 1 else np.concatenate(bands, axis=0)
        r0 = self.y0 - b0 * BAND_ROWS
        out = full[r0:r0 + (self.y1 - self.y0), self.x0:self.x1]
        self._cache[key] = out
        return out


class Effect:
    """Base class of a registered detector effect (see the module docstring)."""

    name: ClassVar[str] = ""
    stages: ClassVar[tuple[Stage, ...]] = ()
    Params: ClassVar[type[EffectParams]] = EffectParams
    #: True when ``apply`` draws from the frame seed (new every frame: row noise, kTC, cosmic rays). The
    #: model of the mean frame (:meth:`detector.Detector.moments`) then skips ``apply`` and adds
    #: :meth:`variance_e2` to the per-pixel variance instead.
    stochastic: ClassVar[bool] = False
    #: True when the effect is a random *hardware* realisation (hardware seed: PRNU, DSNU, defect
    #: positions). A real camera has its own realisation, so the model of the mean frame leaves the
    #: pattern out and adds its :meth:`variance_e2` (maps) or compares its outliers by their counts.
    pattern: ClassVar[bool] = False
    #: How the effect shows in residuals, for ``newtsim diagnose`` (a :class:`detector.signatures.Signature`),
    #: or None when it cannot be diagnosed from one frame.
    signature: ClassVar[object] = None
    #: How a smooth field of the effect combines with the light, for the diagnosis: "additive" (charge or ADU
    #: added whatever the light: sky, straylight, glow, dark and bias patterns), "multiplicative" (a response
    #: to the light: vignetting, flat maps, gains, a mosaic), "" (neither, or not a smooth field). A residual
    #: that scales with the light cannot be an additive field (:func:`scenes.app.compare.judge.kind_gate`).
    field_kind: ClassVar[str] = ""
    #: Parameters at which the effect is the identity (zero strength): the registry-wide contract test
    #: (tests/detector/test_effect_contract.py) renders a frame with them and requires the same bytes as
    #: without the effect. None only with :attr:`no_identity` saying why the effect has no zero strength.
    identity: ClassVar[dict | None] = None
    no_identity: ClassVar[str] = ""
    #: How the effect's signal changes from frame to frame of a series (``newtsim diagnose --series``):
    #: "exposure" (a dark charge: grows with exposure time), "signal" (follows the collected light: a
    #: response, a redistribution), "none" (the same in every frame: bias structure, read-out noise) - all
    #: three are hardware the frames of a series share, fitted with one set of parameters - or "frame"
    #: (changes with the pointing, the sky or the time: fitted frame by frame). None: undeclared (a
    #: plugin), treated as "frame".
    scaling: ClassVar[str | None] = None
    #: COUPLING effects only: rows of the neighbouring tiles the effect needs on each side (its kernel's
    #: reach), or None for the whole read-out window (CTI: a whole column); and the order among COUPLING
    #: effects (0 charge collection: brighter-fatter, 1 transfer: CTI, 2 sense node: IPC)
    halo_rows: ClassVar[int | None] = 0
    coupling_order: ClassVar[int] = 1

    def __init__(self, params: EffectParams, sensor: SensorConfig):
        self.params = params
        self.sensor = sensor
        self.setup()

    def setup(self) -> None:
        """Draw whatever is fixed for the whole frame (the hardware pattern), once."""

    def prepare_frame(self, exptime_s: float, frame_seed: int):
        """Per-frame state shared by all tiles (e.g. the cosmic-ray tracks of this frame), or None.

        Must be a pure function of its arguments and the effect: it is called once per frame and may be
        called again to rebuild the truth of a frame. Tiles read it as ``tile.state[self.name]``.
        """
        return None

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def leaves_uniform(self, level_e: float) -> bool:
        """FIELD stage: True when :meth:`apply` leaves an image of the uniform level ``level_e`` [e-] exactly as
        it is (the chain then does not build the whole image for it: a uniform frame stays a number). False
        unless an effect knows better."""
        return False

    def couple(self, tile: Tile, charge_e: np.ndarray, pad_top: int, pad_bottom: int,
               mean_only: bool = False) -> np.ndarray:
        """COUPLING stage: return the new charge [e-] of ``charge_e`` (the tile's rows with ``pad_top`` /
        ``pad_bottom`` rows of the neighbouring tiles around them). Rows within the effect's reach of an
        edge that is not the frame's may be wrong; the chain crops them. ``mean_only``: the array is the
        model's mean charge (:meth:`detector.Detector.moments`), not a noisy realisation."""
        raise NotImplementedError  # pragma: no cover - abstract

    def variance_e2(self, stage: Stage, tile: Tile, mean_e: np.ndarray) -> float | np.ndarray:
        """Variance [e-^2] a stochastic or pattern effect adds at ``stage`` to a pixel of mean ``mean_e``
        [e-] (before the effect), for the model of the mean frame (:meth:`detector.Detector.moments`)."""
        return 0.0

    def truth(self, state=None) -> dict[str, np.ndarray]:
        """Tables (numpy structured arrays) written as FITS extensions, keyed by extension name.

        ``state`` is what :meth:`prepare_frame` returned for the frame.
        """
        return {}

    @classmethod
    def describe(cls) -> dict:
        """Name, stages, docstring and parameter schema (units, defaults, bounds) for docs and the CLI.

        Every numeric parameter carries a machine-readable ``unit`` (:func:`param_unit`): the one its field
        declares (``json_schema_extra``), else the bracketed unit of its description, else its name's suffix."""
        schema = cls.Params.model_json_schema()
        for key, prop in schema.get("properties", {}).items():
            if "unit" not in prop and _is_numeric(prop):
                prop["unit"] = param_unit(key, prop.get("description") or "")
        return {"name": cls.name, "stages": [s.name for s in cls.stages],
                "doc": (cls.__doc__ or "").strip(), "params": schema}


def _is_numeric(prop: dict) -> bool:
    kinds = [prop] + prop.get("anyOf", []) + prop.get("oneOf", [])
    return any(k.get("type") in ("number", "integer")
               or (k.get("type") == "array" and k.get("items", {}).get("type") in ("number", "integer"))
               for k in kinds)


#: units read from a parameter name's suffix when its description has no bracketed unit
_SUFFIX_UNITS = (("_e_per_s", "e-/s"), ("_per_px", "1/pixel"), ("_adu", "ADU"), ("_px", "pixel"), ("_s", "s"),
                 ("_k", "K"), ("_e", "e-"), ("_deg", "deg"), ("_mm", "mm"))


def param_unit(name: str, description: str) -> str:
    """The unit of a numeric parameter: the last bracketed unit of its description (``"... [e-/s]"``; a
    bracket holding a comma is an interval, not a unit), else its name's suffix (``_s``: s), else "1"
    (a count, an index or a ratio)."""
    units = [u.strip() for u in re.findall(r"\[([^\[\]]+)\]", description) if "," not in u]
    if units:
        return units[-1]
    return next((u for suffix, u in _SUFFIX_UNITS if name.endswith(suffix)), "1")


_REGISTRY: dict[str, type[Effect]] = {}


def register_effect(cls: type[Effect]) -> type[Effect]:
    """Class decorator: add an effect to the catalogue under ``cls.name``."""
    if not cls.name or not cls.stages:
        raise TypeError(f"effect class {cls.__name__} must define 'name' and 'stages'")
    _REGISTRY[cls.name] = cls
    return cls


#: the install state (:func:`_install_state`) of the last entry-point scan: the scan is repeated only when it
#: changes (a diagnosis asks for the registry hundreds of times; each scan reads every installed distribution's
#: metadata, ~7 ms)
_SCANNED: tuple | None = None


def _install_state() -> tuple:
    """What the ``newtsim.effects`` entry points can change with: the discovery function and the modification
    time [ns] of every import-path entry (installing, removing or reinstalling a distribution adds or removes
    its metadata directory there; the same test by which ``importlib.metadata`` keeps its own directory
    listings, ``FastPath.mtime``)."""
    from importlib.metadata import entry_points

    times = []
    for entry in sys.path:
        try:
            times.append(os.stat(entry or ".").st_mtime_ns)
        except OSError:
            times.append(None)
    return entry_points, tuple(sys.path), tuple(times)


def _load_entry_points() -> None:
    global _SCANNED
    state = _install_state()
    if _SCANNED == state:
        return
    entry_points = state[0]
    for ep in entry_points(group="newtsim.effects"):
        if ep.name not in _REGISTRY:
            cls = ep.load()
            if getattr(cls, "name", None) != ep.name:
                cls.name = ep.name
            register_effect(cls)
    _SCANNED = state


def registry() -> dict[str, type[Effect]]:
    """All registered effects (built-in, decorated and from the ``newtsim.effects`` entry points)."""
    _load_entry_points()
    return dict(_REGISTRY)


def build_effects(tables: dict[str, dict], sensor: SensorConfig, *, file: str | None = None) -> list[Effect]:
    """Instantiate the effects of a scene's ``[effects]`` table, validating every parameter."""
    from ..config import validate

    known = registry()
    out = []
    for name, params in (tables or {}).items():
        if name not in known:
            raise DetectorError(f"unknown effect {name!r}", key=f"effects.{name}",
                                expected="one of " + ", ".join(sorted(known)), file=file)
        cls = known[name]
        p = validate(cls.Params, params or {}, prefix=f"effects.{name}", file=file)
        try:
            out.append(cls(p, sensor))
        except DetectorError as exc:  # an effect refusing this sensor or a file: name the scene file
            if exc.file is None and file is not None and (exc.key or "").startswith("effects."):
                raise DetectorError(exc.message, key=exc.key, expected=exc.expected, file=file) from None
            raise
    return out

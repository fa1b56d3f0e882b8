"""Scene files (TOML, DESIGN.md "Scene file"): loading, ``--set`` overrides, validation, resolution.

Every user mistake becomes a :class:`SceneError` naming the file, the dotted key and what was expected.
"""

from __future__ import annotations

import copy
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import tomli_w
import tomllib
from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, field_validator

from detector import SensorConfig, make_sensor, registry
from detector.config import validate
from optics.design import BUILTIN as BUILTIN_DESIGNS
from optics.design import OpticsError, load_design

from .errors import SceneError
from .objects import object_from_table, observer_from_table
from .projection import sip_from_table
from .straylight import StraylightCfg, is_traced_straylight, straylight_config

BUILTIN_SCENES = Path(__file__).with_name("data")


class _Table(BaseModel):
    model_config = ConfigDict(extra="forbid")


class TelescopeCfg(_Table):
    """``[telescope]``. ``distortion``: ``"none"`` (gnomonic TAN), ``"optics"`` (SIP fitted to the design's
    ray-traced field, cached by the optics) or ``"sip"`` (the coefficients of ``[telescope.sip]``); the
    ``[telescope.sip]`` table is checked by :func:`scenes.projection.sip_from_table`; its
    ``radial_k_per_px2`` adds a radial term ``r' = r (1 + k r^2)`` to either form (``[effects.distortion]``
    of a scene becomes that key when the scene is loaded, :func:`resolve_effect_keys`). ``parity``: the
    handedness of the frame's WCS (:func:`scenes.projection.tan_wcs`); ``pointing.roll_deg`` keeps its
    meaning (where north points on the detector), ``+1`` puts east on the other side."""

    design: str = "art"
    pixel_scale_arcsec: float | None = Field(None, gt=0, le=3600, description="plate-scale override [arcsec/pixel]")
    parity: Literal[-1, 1] = Field(-1, description="sign of det(CD) of the frame's WCS [1]: -1 the sky as seen "
                                   "looking up (north up, east left), +1 its east-west mirror image (an odd number "
                                   "of reflections before the camera, or a camera reading its columns reversed)")
    distortion: Literal["none", "optics", "sip"] = "none"
    sip: dict[str, Any] | None = None

    @field_validator("parity", mode="before")
    @classmethod
    def _parity_not_bool(cls, value):
        if isinstance(value, bool):  # true == 1 in Python: refuse it explicitly
            raise ValueError("-1 or 1 (not true/false)")  # noqa: TRY004  (pydantic reports ValueError)
        return value


class PointingCfg(_Table):
    ra_deg: float = Field(120.95115, ge=0, lt=360)
    dec_deg: float = Field(-29.25022, ge=-90, le=90)
    roll_deg: float = Field(0.0, ge=-360, le=360)
    epoch: str = "2023-02-01T22:00:00"

    @field_validator("epoch", mode="before")
    @classmethod
    def _toml_datetime(cls, value):
        """An unquoted TOML date-time (``epoch = 2023-02-01T22:00:00``) is the same time as the quoted text."""
        import datetime as dt

        if isinstance(value, dt.datetime):
            if value.tzinfo is not None:
                value = value.astimezone(dt.timezone.utc).replace(tzinfo=None)
            return value.isoformat()
        return value

    @field_validator("epoch")
    @classmethod
    def _epoch(cls, value: str) -> str:
        import warnings

        from astropy.time import Time

        try:
            with warnings.catch_warnings():  # ERFA's "dubious year" for a far epoch: a warning, not an error
                warnings.simplefilter("ignore")
                Time(value, format="isot", scale="utc")
        except ValueError:
            raise ValueError("an ISO UTC time like 2023-02-01T22:00:00") from None
        return value


class ExposureCfg(_Table):
    """``[exposure]``. ``tracking``: ``"sidereal"`` (the mount follows the stars), ``"rate"`` (the boresight
    moves at ``rate_ra_deg_s`` = dRA/dt cos(Dec) and ``rate_dec_deg_s`` = dDec/dt along a great circle, the
    convention of ``[[objects]]``: an object with the same rates stays put), ``"none"`` (drive off: the stars
    trail at the sidereal rate)."""

    time_s: float = Field(2.0, ge=0, le=1e6, description="exposure time [s]")
    frame: Literal["light", "dark", "bias"] = "light"
    tracking: Literal["sidereal", "rate", "none"] = "sidereal"
    rate_ra_deg_s: float = Field(0.0, ge=-180, le=180, description="tracking rate dRA/dt cos(Dec) [deg/s]")
    rate_dec_deg_s: float = Field(0.0, ge=-180, le=180, description="tracking rate dDec/dt [deg/s]")
    seed: int | None = Field(None, ge=0, description="frame seed (noise); --seed overrides; random if absent")


class SkyCfg(_Table):
    """``[sky]``. ``catalog``: ``"builtin"`` (offline Gaia DR3 + Hipparcos to G = 10, model stars beyond),
    ``"gaia"`` (the Gaia archive, cached) or a CSV/ECSV/FITS star table, relative to the scene file's folder.
    ``star_seed`` fixes the synthetic faint stars (the same in every frame of a scene)."""

    background_mag_arcsec2: float | None = Field(21.0, ge=5, le=35, description="sky brightness [AB mag/arcsec^2]")
    stars: bool = False
    star_mag_limit: float = Field(16.0, le=25, description="faintest Gaia G rendered [mag]")
    star_seed: int = Field(0, ge=0, description="seed of the synthetic faint-star population")
    catalog: str = "builtin"
    flat_e_per_s: float | None = Field(None, ge=0, description="uniform illumination (flat screen) [e-/pixel/s]")
    source_flux_scale: float = Field(1.0, gt=0, le=1e3, description="factor on every source's flux (stars and "
                                     "objects) [1]: the photometric zero point's error, the atmosphere's "
                                     "transparency; what `diagnose` refits as the sources' zero point")


class PsfCfg(_Table):
    """``[psf]``: the point-spread function of the sources (thesis eqs. 4 and 48), integrated over pixels.

    ``model`` ``"gaussian"`` (sigma = FWHM / 2.3548), ``"moffat"`` ((1 + r^2/alpha^2)^-beta) or ``"optics"``
    (the design's PSF grid, :mod:`scenes.image.gridpsf`: ``grid = [nx, ny]`` field points, or a PSF cube
    ``grid_file``; ``seeing_fwhm_arcsec``: Gaussian seeing convolved with it); ``jitter_rms_arcsec``:
    Gaussian pointing jitter, rms per axis: a short form of ``[effects.jitter]`` (the one jitter mechanism),
    into which the loaded scene turns it (:func:`resolve_effect_keys`; it then reads 0 here)."""

    model: Literal["gaussian", "moffat", "optics"] = "gaussian"
    fwhm_arcsec: float = Field(2.5, gt=0, le=600, description="PSF full width at half maximum [arcsec]")
    beta: float = Field(4.765, gt=1, le=100, description="Moffat exponent (4.765: Kolmogorov turbulence)")
    jitter_rms_arcsec: float = Field(0.0, ge=0, le=600, description="pointing jitter, rms per axis [arcsec]")
    seeing_fwhm_arcsec: float = Field(0.0, ge=0, le=600, description="optics model: Gaussian seeing FWHM [arcsec]")
    grid: tuple[int, int] = Field((3, 3), description="optics model: PSF field points along x and y")
    grid_file: str | None = Field(None, description="optics model: a PSF cube (optics.psf.write_psf_fits) instead")

    @field_validator("grid")
    @classmethod
    def _grid(cls, value):
        if not all(1 <= n <= 15 for n in value):
            raise ValueError("two counts, each 1..15")
        return value


class MaskCfg(_Table):
    """``[mask]``: pixels of the measured frame that no comparison uses (extended sources: galaxies, nebulae;
    saturation bleeds; a satellite streak the scene does not model). ``file``: a FITS image of the measured
    frame's size (after ``[measured] trim``), non-zero = masked, relative to the scene file; ``hdu``: its
    image HDU (default: the first image). Compare and diagnose set those pixels to NaN when they read the
    measured frame (docs/reliability.md: NaN pixels are left out of the fit and every statistic)."""

    file: str | list[str] = Field(description="FITS mask (non-zero = masked), or several (their union) [path]")
    hdu: int | str | None = Field(None, description="HDU index or EXTNAME of the mask (default: the first image)")


class MeasuredCfg(_Table):
    """``[measured]``: how the measured frame compared with this scene is read. ``hdu``: the image HDU of a
    multi-extension file (index or EXTNAME; default the first image); ``trim``: the FITS section (1-based,
    inclusive, ``"[x1:x2,y1:y2]"``, as ``TRIMSEC``/``DATASEC``) of the light-sensitive pixels of a raw frame
    with prescan / overscan columns: only those pixels are compared."""

    hdu: int | str | None = Field(None, description="HDU index or EXTNAME of the measured image")
    trim: str | None = Field(None, description="FITS section [x1:x2,y1:y2] of the pixels compared (1-based)")

    @field_validator("trim")
    @classmethod
    def _section(cls, value):
        if value is None:
            return value
        from .measured import parse_section

        parse_section(value)  # ValueError names what is expected
        return value


@dataclass(frozen=True)
class SceneParts:
    """The typed parts of a validated scene, built once when it is loaded (:attr:`Scene.parts`).

    Attributes
    ----------
    sensor : the resolved :class:`detector.SensorConfig` of ``[detector]``
    observer : ``[observer]`` as a :class:`scenes.objects.GroundSite` / :class:`SpaceObserver`, or None
    objects : the ``[[objects]]`` as :class:`scenes.objects.RateObject` / :class:`TleObject`, in file order
    straylight : the scene's ray-traced straylight (``[effects.straylight]`` with ``pst``), or None
    effect_tables : the ``[effects.NAME]`` tables the detector's registry builds (the ray-traced straylight,
        which the scene evaluates, is not among them)
    """

    sensor: SensorConfig
    observer: Any
    objects: tuple
    straylight: StraylightCfg | None
    effect_tables: dict


class Scene(_Table):
    """A validated scene.

    The tables stay readable as in the file (``scene.detector``, ``scene.objects``, ``scene.effects`` are
    dicts: outside code and ``diagnose --apply`` dump them back); :attr:`parts` holds them typed, parsed once
    by :func:`check_scene` (and again only if a table was changed after loading).
    """

    telescope: TelescopeCfg = TelescopeCfg()
    detector: dict[str, Any] = Field(default_factory=lambda: {"preset": "imx411"})
    pointing: PointingCfg = PointingCfg()
    exposure: ExposureCfg = ExposureCfg()
    sky: SkyCfg = SkyCfg()
    psf: PsfCfg = PsfCfg()
    observer: dict[str, Any] | None = None
    objects: list[dict[str, Any]] = Field(default_factory=list)
    effects: dict[str, dict[str, Any]] = Field(default_factory=dict)
    mask: MaskCfg | None = None
    measured: MeasuredCfg | None = None
    source: str = Field("<built-in>", exclude=True)
    _parts: SceneParts | None = PrivateAttr(None)
    _parts_key: str | None = PrivateAttr(None)
    _notes: list = PrivateAttr(default_factory=list)

    def _key(self) -> str:
        return json.dumps(self.model_dump(mode="json"), sort_keys=True, default=str)

    @property
    def parts(self) -> SceneParts:
        """The typed parts (:class:`SceneParts`); a scene built in code, or changed after loading, is checked
        (:func:`check_scene`) the first time they are asked for."""
        if self._parts is None or self._parts_key != self._key():
            check_scene(self)
        return self._parts

    @property
    def resolution_notes(self) -> list[str]:
        """What the short forms of the file became (``psf.jitter_rms_arcsec`` -> ``[effects.jitter]``, ...)."""
        return list(self._notes)

    def sensor(self) -> SensorConfig:
        """The resolved sensor (a frozen :class:`detector.SensorConfig`, built once at loading)."""
        if self._parts is not None and self._parts_key == self._key():
            return self._parts.sensor
        det = dict(self.detector)
        preset = det.pop("preset", "imx411")
        return make_sensor(preset, det, file=self.source)

    def resolved(self) -> dict:
        """The scene with every default filled in, including the resolved sensor (for the FITS file)."""
        d = self.model_dump(mode="json", exclude_none=True)
        d["detector"] = {"preset": self.detector.get("preset", "imx411"),
                         **self.sensor().model_dump(mode="json", exclude_none=True)}
        return d

    def resolved_text(self) -> str:
        """:meth:`resolved` as TOML, headed by a comment line per short form the file used and what it
        became (the ``SCENE`` extension of a frame)."""
        head = "".join(f"# {n}\n" for n in self._notes)
        return head + tomli_w.dumps(self.resolved())

    def to_toml(self) -> str:
        return tomli_w.dumps(self.model_dump(mode="json", exclude_none=True))


def parse_value(text: str) -> Any:
    """A ``--set`` value as TOML (numbers, booleans, strings, arrays, inline tables), else a plain string."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def apply_overrides(data: dict, assignments: list[str], *, file: str) -> dict:
    """Apply ``KEY=VALUE`` overrides (dotted keys, e.g. ``exposure.time_s=150``) to a scene dict."""
    out = copy.deepcopy(data)
    for item in assignments or []:
        if "=" not in item:
            raise SceneError(f"--set {item!r} has no '='", key=item, expected="KEY=VALUE, e.g. exposure.time_s=150",
                             file=file)
        key, value = item.split("=", 1)
        parts = key.strip().split(".")
        if not all(parts):
            raise SceneError("empty key part", key=key, expected="a dotted key like exposure.time_s", file=file)
        node = out
        for part in parts[:-1]:
            nxt = node.setdefault(part, {})
            if not isinstance(nxt, dict):
                raise SceneError(f"'{part}' is a value, not a table", key=key, expected="a dotted path to a key",
                                 file=file)
            node = nxt
        node[parts[-1]] = parse_value(value.strip())
    return out


def builtin_scene_names() -> list[str]:
    return sorted(p.stem for p in BUILTIN_SCENES.glob("*.toml"))


def read_toml(p: Path, expected: str) -> dict:
    """A TOML file's tables; an undecodable or unreadable file is one :class:`SceneError` naming it."""
    try:
        return tomllib.loads(p.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise SceneError(f"not valid TOML ({exc})", file=str(p), expected=expected) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SceneError(f"cannot read ({exc})", file=str(p)) from None


def load_scene(path_or_name: str, overrides: list[str] | None = None) -> Scene:
    """Load, override and validate a scene (a path, or the name of a built-in scene such as ``default``)."""
    p = Path(path_or_name)
    if not p.is_file() and (BUILTIN_SCENES / f"{path_or_name}.toml").is_file():
        p = BUILTIN_SCENES / f"{path_or_name}.toml"
    file = str(p)
    if p.is_dir():
        raise SceneError("is a directory", file=file, expected="a scene TOML file or a built-in scene: "
                         + ", ".join(builtin_scene_names()))
    if p.exists() and not p.is_file():
        raise SceneError("is not a regular file", file=file, expected="a scene TOML file")
    if not p.is_file():
        raise SceneError("scene file not found", file=file,
                         expected="a scene TOML path or a built-in scene: " + ", ".join(builtin_scene_names()))
    data = read_toml(p, "a TOML scene file")
    if not data:
        raise SceneError("the scene is empty (no table, no key)", file=file,
                         expected="at least one table such as [exposure], or the built-in scene 'default'")
    data = apply_overrides(data, overrides or [], file=file)
    data["source"] = file
    scene = validate(Scene, data, file=file)
    check_scene(scene)  # [detector] and every other table, once, into scene.parts
    return scene


def scene_dir(scene: Scene) -> Path | None:
    """The absolute folder of the scene file (None for a built-in scene or a scene built in code)."""
    file = scene.source
    return Path(os.path.abspath(Path(file).parent)) if file and file != "<built-in>" else None


def resolve_path(value: str, base: Path | None) -> Path:
    """A file path of a scene as an absolute path: ``~`` expanded, relative paths taken from ``base`` (the
    scene file's folder, :func:`scene_dir`), else from the working directory; ``..`` normalised, symbolic
    links kept (``os.path.abspath``, not ``Path.resolve``)."""
    p = Path(value).expanduser()
    if not p.is_absolute() and base is not None:
        p = base / p
    return Path(os.path.abspath(p))


#: effect parameters that hold a file path (resolved like the catalogue); values that are keywords, not files
EFFECT_PATH_SUFFIX = "_file"
EFFECT_PATH_KEYWORDS = ("optics",)


def _is_effect_path_key(key: str) -> bool:
    return key == "path" or key.endswith(EFFECT_PATH_SUFFIX)


def check_scene(scene: Scene) -> None:
    """Cross-key checks and the tables validated by their own modules, each error naming its key.

    ``[[objects]]`` entries go through :func:`scenes.objects.object_from_table`, ``[observer]`` through
    :func:`scenes.objects.observer_from_table`.

    File paths. Every file a scene names (``sky.catalog``, ``psf.grid_file``, ``telescope.design`` when it
    is a design TOML, ``tle_file`` of ``[[objects]]`` and ``[observer]``, and the effect parameters named
    ``path`` or ``*_file``, e.g. ``effects.bias_map.path``, ``effects.vignetting.map_file``) is relative to
    the scene file's folder and is written back **absolute**: the validated scene (``Scene.resolved``,
    the FITS ``SCENE`` extension, ``diagnose --apply``) then names the same files from any working
    directory and from any folder it is written to. (Writing them back relative to a *new* scene's folder
    would need the writer to know that folder; absolute paths need nothing and the user's own file keeps
    its relative paths.)
    """
    file = scene.source
    base = scene_dir(scene)
    det = dict(scene.detector)
    sensor = make_sensor(det.pop("preset", "imx411"), det, file=file)  # [detector], naming its keys
    exp = scene.exposure
    if exp.tracking == "rate" and not {"rate_ra_deg_s", "rate_dec_deg_s"} & exp.model_fields_set:
        raise SceneError("tracking = 'rate' without a rate", key="exposure.rate_ra_deg_s", file=file,
                         expected="rate_ra_deg_s and/or rate_dec_deg_s [deg/s] with tracking = 'rate' (an absent "
                         "one is 0)")
    if exp.tracking != "rate":
        for k in ("rate_ra_deg_s", "rate_dec_deg_s"):
            if getattr(exp, k) != 0:
                raise SceneError(f"a tracking rate with tracking = {exp.tracking!r}", key=f"exposure.{k}", file=file,
                                 expected="tracking = 'rate' with rate_ra_deg_s / rate_dec_deg_s, or no rates")
    cat = scene.sky.catalog
    if cat not in ("builtin", "gaia"):
        p = resolve_path(cat, base)
        if scene.sky.stars and not p.is_file():
            raise SceneError(f"star catalogue {str(p)!r} not found", key="sky.catalog", file=file,
                             expected="'builtin', 'gaia' or a CSV/ECSV/FITS file (relative to the scene file)")
        scene.sky.catalog = str(p)
    if scene.mask is not None:
        paths = []
        for v in [scene.mask.file] if isinstance(scene.mask.file, str) else scene.mask.file:
            p = resolve_path(v, base)
            if not p.is_file():
                raise SceneError(f"mask file {str(p)!r} not found", key="mask.file", file=file,
                                 expected="a FITS image, non-zero = masked (relative to the scene file)")
            paths.append(str(p))
        scene.mask.file = paths[0] if isinstance(scene.mask.file, str) else paths
    _resolve_design(scene, base)
    observer = observer_from_table(scene.observer, file=file, base_dir=base)
    if isinstance(scene.observer, dict) and isinstance(scene.observer.get("tle_file"), str):
        scene.observer["tle_file"] = str(resolve_path(scene.observer["tle_file"], base))
    objects = []
    for i, table in enumerate(scene.objects):
        objects.append(object_from_table(table, i, file=file, base_dir=base))
        if isinstance(table.get("tle_file"), str):
            table["tle_file"] = str(resolve_path(table["tle_file"], base))
    for table in scene.effects.values():
        for key, value in list((table or {}).items()) if isinstance(table, dict) else ():
            if _is_effect_path_key(key) and isinstance(value, str) and value not in EFFECT_PATH_KEYWORDS:
                table[key] = str(resolve_path(value, base))
    resolve_effect_keys(scene, sensor)
    _check_optics_keys(scene, base)
    straylight = None
    tables = dict(scene.effects)
    if "straylight" in tables and is_traced_straylight(tables["straylight"]):
        straylight = straylight_config(tables.pop("straylight"), file=file)
    scene._parts = SceneParts(sensor, observer, tuple(objects), straylight, tables)
    scene._parts_key = scene._key()


# ------------------------------------------------------------------------- one mechanism per effect
#: the jitter effect's bound on either width [sensor px] (detector.effects.image_plane.JitterParams)
JITTER_MAX_PX = 50.0


def resolve_effect_keys(scene: Scene, sensor: SensorConfig) -> None:
    """Turn the scene's second spelling of an effect into its one mechanism (in place; idempotent).

    * ``[psf] jitter_rms_arcsec = J`` (isotropic Gaussian jitter, rms per axis) becomes ``[effects.jitter]``
      (the registered image-plane jitter, :class:`detector.effects.image_plane.Jitter`) with
      ``sigma = J / s`` [sensor px] on both axes (``s`` the plate scale [arcsec/px]); with an
      ``[effects.jitter]`` table already there the covariances add (convolving two Gaussians adds their
      covariances: an isotropic ``sigma_J^2 I`` adds to both principal variances and keeps the axes), so
      ``sigma_major' = hypot(sigma_major, J / s)``, ``sigma_minor' = hypot(sigma_minor, J / s)``.
      ``[psf] jitter_rms_arcsec`` then reads 0.
    * ``[effects.distortion] k_per_px2 = k`` (radial distortion ``r' = r (1 + k r^2)`` about the optical axis)
      becomes ``[telescope.sip] radial_k_per_px2`` (added to a value already there: two small radial
      distortions compose to first order as the sum of their k), and its decentering terms ``p1_per_px``,
      ``p2_per_px`` become ``decentering_p1_per_px``, ``decentering_p2_per_px`` (summed likewise), which the
      frame's SIP then carries
      (:func:`scenes.projection.with_radial`): the sources are drawn where it puts them and the WCS says so.
      ``distortion = "none"`` becomes ``"sip"``. The ``[effects.distortion]`` table is removed.

    Each change is noted (:attr:`Scene.resolution_notes`): the ``SCENE`` extension of a frame starts with
    those notes as TOML comments.
    """
    file = scene.source
    effects = registry()
    j = scene.psf.jitter_rms_arcsec
    if j > 0:
        try:
            design = load_design(scene.telescope.design)
        except OpticsError as exc:
            raise SceneError(str(exc), key="telescope.design", file=file) from None
        scale = scene.telescope.pixel_scale_arcsec or design.pixel_scale_arcsec(sensor.pixel_pitch_um)
        s = j / scale
        old = scene.effects.get("jitter")
        if old is not None:
            p = validate(effects["jitter"].Params, old, prefix="effects.jitter", file=file)
            major, minor, angle = math.hypot(p.sigma_major_px, s), math.hypot(p.sigma_minor_px, s), p.angle_deg
        else:
            major, minor, angle = s, s, 0.0
        if major > JITTER_MAX_PX:
            raise SceneError(f"{j:g} arcsec of jitter is {major:.4g} sensor pixels", key="psf.jitter_rms_arcsec",
                             file=file, expected=f"at most {JITTER_MAX_PX:g} pixels of jitter in all "
                             f"({JITTER_MAX_PX * scale:.4g} arcsec at {scale:.4g} arcsec/pixel)")
        scene.effects["jitter"] = {"sigma_major_px": major, "sigma_minor_px": minor, "angle_deg": angle}
        scene.psf.jitter_rms_arcsec = 0.0
        scene._notes.append(f"psf.jitter_rms_arcsec = {j:g} arcsec ({s:.6g} px at {scale:.6g} arcsec/px) became "
                            f"[effects.jitter]" + (" (added to its covariance)" if old is not None else ""))
    if "distortion" in scene.effects:
        p = validate(effects["distortion"].Params, scene.effects["distortion"], prefix="effects.distortion", file=file)
        del scene.effects["distortion"]
        k, p1, p2 = float(p.k_per_px2), float(p.p1_per_px), float(p.p2_per_px)
        tel = scene.telescope
        terms = {"radial_k_per_px2": k, "decentering_p1_per_px": p1, "decentering_p2_per_px": p2}
        if any(terms.values()):
            sip = dict(tel.sip or {})
            for key, v in terms.items():
                if v:
                    sip[key] = float(sip.get(key, 0.0)) + v
            tel.sip = sip
            if tel.distortion == "none":
                tel.distortion = "sip"
        given = ", ".join(f"{key} = {v:g}" for key, v in terms.items() if v)
        scene._notes.append(f"[effects.distortion] became [telescope.sip] {given} (distortion = '{tel.distortion}'): "
                            "the frame's SIP carries it" if given else
                            "[effects.distortion] at the identity (k = p1 = p2 = 0) was dropped")


def _resolve_design(scene: Scene, base: Path | None) -> None:
    """``[telescope] design``: a built-in name stays; a design TOML path becomes absolute (scene folder first,
    then the working directory, where it was looked up before)."""
    d = scene.telescope.design
    if (BUILTIN_DESIGNS / f"{d}.toml").is_file():
        return
    p = resolve_path(d, base)
    if not p.is_file() and Path(d).expanduser().is_file():
        p = Path(os.path.abspath(Path(d).expanduser()))
    if p.is_file():
        scene.telescope.design = str(p)


def _check_optics_keys(scene: Scene, base: Path | None) -> None:
    """``[telescope] distortion`` / ``[telescope.sip]`` and the optics ``[psf]`` keys."""
    file = scene.source
    tel = scene.telescope
    if tel.distortion == "none" and tel.sip is not None:
        raise SceneError("a [telescope.sip] table with distortion = 'none'", key="telescope.distortion", file=file,
                         expected="distortion = 'sip' (coefficients from the table) or 'optics'")
    if tel.distortion == "sip" and tel.sip is None:
        raise SceneError("distortion = 'sip' without a [telescope.sip] table", key="telescope.sip", file=file,
                         expected="a table with order and coefficients a_p_q / b_p_q")
    if tel.sip is not None:
        sip_from_table(tel.sip, file=file, allow_coefficients=tel.distortion == "sip")
    if tel.parity == 1:  # the optics' PSF grid and straylight maps are oriented for parity -1 only
        if scene.psf.model == "optics":
            raise SceneError("parity = +1 with the optics PSF grid (its stamps are not mirrored yet)",
                             key="telescope.parity", file=file, expected="parity = -1, or psf.model = 'gaussian' / "
                             "'moffat'")
        if (scene.effects.get("straylight") or {}).get("pst") == "optics":
            raise SceneError("parity = +1 with the ray-traced straylight maps (not mirrored yet)",
                             key="telescope.parity", file=file, expected="parity = -1, or a PST value/table")
    psf = scene.psf
    given = psf.model_fields_set
    if psf.model == "optics":
        for k in ("fwhm_arcsec", "beta"):
            if k in given:
                raise SceneError(f"{k} with model = 'optics'", key=f"psf.{k}", file=file,
                                 expected="seeing_fwhm_arcsec / jitter_rms_arcsec with the optics PSF grid")
        if psf.grid_file is not None:
            p = resolve_path(psf.grid_file, base)
            if not p.is_file():
                raise SceneError(f"PSF cube {str(p)!r} not found", key="psf.grid_file", file=file,
                                 expected="a FITS PSF cube written by optics.psf.write_psf_fits (relative to the "
                                 "scene file)")
            psf.grid_file = str(p)
    else:
        for k in ("seeing_fwhm_arcsec", "grid", "grid_file"):
            if k in given:
                raise SceneError(f"{k} with model = {psf.model!r}", key=f"psf.{k}", file=file,
                                 expected="model = 'optics' (the optics PSF grid)")

"""Many frames on Dask: parameter sweeps x time sequences x Monte-Carlo draws (``newtsim batch``).

A batch file (TOML, ``docs/scenes_batch.md``) names a base scene, a root seed and an output folder, and
optionally ``[overrides]`` (merged into the scene), ``[[sweep]]`` tables (their cartesian product),
a ``[sequence]`` (frames stepped in time by a cadence) and ``[montecarlo]`` draws (repeats with other
seeds). Frame ``i`` of the ``N = sweep points x sequence frames x draws`` frames is::

    i = (p * frames + k) * draws + d         p: sweep point (first [[sweep]] slowest), k: step, d: draw

and is rendered with the ``--set`` overrides of its sweep point and step and the seed
:func:`frame_seed` (``SeedSequence(root).spawn(N)[i]``), so ``newtsim render SCENE --seed S --set ...``
with the manifest's seed and ``set`` list writes the same bytes.

Each frame is one Dask task (:func:`render_frame`) that renders on one thread (the cluster supplies the
parallelism) and writes ``frame_IIII.fits`` atomically (a temporary name in the same folder, renamed when
complete). The client keeps ``manifest.json`` (per frame: overrides, seed, status, error, wall time,
sha256) up to date as frames finish; a re-run skips the frames whose file and manifest entry match.
A frame that fails (a bad override, a scene that cannot render) is reported in the manifest and the
summary; the others go on.

With labels (``[batch] labels`` or ``--labels FORMAT[,FORMAT]``) the batch writes a dataset
(docs/detection_bench.md): each frame's label files next to it (``frame_IIII.coco.json``, ``.satnet.json``,
``.yolo.txt``, as ``render --labels`` writes them; ``fits`` adds the ``LABELS`` extension), one annotation
file per format for the whole dataset (``dataset.coco.json`` with image id = frame index + 1,
``dataset.satnet.json``) rebuilt from the frames done at the end of every run, and each frame's split
(train/val/test, :func:`frame_split`: from its seed) in the manifest and in ``train.txt``/``val.txt``/``test.txt``.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import logging
import math
import os
import re
import shlex
import socket
import sys
import time
import traceback
import uuid
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w
import tomllib
from pydantic import Field

from detector import DetectorError
from detector.config import validate
from detector.jsonable import jsonable
from scenes.app.quicklook import write_png
from scenes.app.render import render
from scenes.image.motion import Boresight
from scenes.objects.frames import east_north, radec_to_unit, unit_to_radec
from scenes.scene import BUILTIN_SCENES, Scene, SceneError, _Table, load_scene

__all__ = [
    "SPLITS",
    "Batch",
    "FrameSpec",
    "frame_seed",
    "frame_sets",
    "frame_split",
    "load_batch",
    "plan",
    "render_frame",
    "run_batch",
    "sequence_overrides",
    "toml_inline",
]

MAX_FRAMES = 1_000_000
MANIFEST = "manifest.json"
MANIFEST_VERSION = 1
_SAVE_EVERY_S = 1.0  # the manifest is rewritten at most this often while frames finish (and at the end)
SPLITS = ("train", "val", "test")
SPLIT_FRACTIONS = (0.8, 0.1, 0.1)  # default [batch] split: train, val, test
DATASET_FILES = {"coco": "dataset.coco.json", "satnet": "dataset.satnet.json"}
_DOTTED = re.compile(r"^[A-Za-z0-9_-]+(\.[A-Za-z0-9_-]+)*$")


# ------------------------------------------------------------------------------------------------ schema
class BatchCfg(_Table):
    """``[batch]``: the base scene, the output folder, the root seed and the render options."""

    scene: str = Field(description="base scene: a TOML path relative to the batch file, or a built-in name")
    output_dir: str | None = Field(None, description="output folder, relative to the current directory")
    seed: int = Field(ge=0, lt=2 ** 63, description="root seed: frame i gets frame_seed(seed, i)")
    noiseless: bool = False
    expected: bool = False
    png: bool = False
    labels: list[str] = Field(default_factory=list,
                              description="label formats (coco, satnet, yolo, fits): the batch writes a dataset")
    split: list[float] = Field(default_factory=lambda: list(SPLIT_FRACTIONS), min_length=3, max_length=3,
                               description="fractions of frames in train, val, test (>= 0, sum 1)")


class SweepCfg(_Table):
    """``[[sweep]]``: one scene key (or several keys varied together) and its values."""

    key: str | list[str]
    values: list[Any]

    @property
    def keys(self) -> list[str]:
        return [self.key] if isinstance(self.key, str) else list(self.key)

    def points(self) -> list[dict[str, Any]]:
        return [dict(zip(self.keys, v if isinstance(self.key, list) else [v])) for v in self.values]


class SequenceCfg(_Table):
    """``[sequence]``: ``frames`` exposures starting every ``cadence_s`` seconds from the scene's epoch."""

    frames: int = Field(ge=1, le=MAX_FRAMES)
    cadence_s: float = Field(gt=0, le=1e9, description="time between exposure starts [s]")


class MonteCarloCfg(_Table):
    """``[montecarlo]``: ``draws`` repeats of each frame with their own seeds."""

    draws: int = Field(ge=1, le=MAX_FRAMES)


class BatchFile(_Table):
    batch: BatchCfg
    overrides: dict[str, Any] = Field(default_factory=dict)
    sweep: list[SweepCfg] = Field(default_factory=list)
    sequence: SequenceCfg | None = None
    montecarlo: MonteCarloCfg | None = None


# ----------------------------------------------------------------------------------------- frame specs
@dataclass(frozen=True)
class FrameSpec:
    """Everything a worker needs to render one frame (picklable, no open files)."""

    index: int
    file: str  # absolute output path
    scene: str  # absolute scene path or a built-in name
    sets: tuple[str, ...]  # --set overrides: [overrides], the command line's --set, the sweep point
    overrides: dict  # the sweep point, {key: value}
    step: int  # sequence step k (exposure start = epoch + k cadence_s)
    cadence_s: float
    draw: int
    seed: int
    noiseless: bool = False
    expected: bool = False
    png: bool = False
    scene_sha256: str = ""
    labels: tuple[str, ...] = ()  # label formats (scenes.app.bench.formats.FORMATS)
    split: str = ""  # train, val or test (frame_split of the seed)

    @property
    def spec_sha256(self) -> str:
        """What determines the frame's bytes (scene content, overrides, step, seed, options)."""
        d = asdict(self)
        for k in ("index", "file", "scene"):
            d.pop(k)
        if not self.labels:  # a frame without labels does not depend on them (nor on its split)
            d.pop("labels")
            d.pop("split")
        return hashlib.sha256(json.dumps(d, sort_keys=True, default=str).encode()).hexdigest()


@dataclass
class Batch:
    """A loaded batch file: its settings and the frames it makes."""

    path: str
    cfg: BatchFile
    scene: str
    scene_sha256: str
    output_dir: Path
    frames: list[FrameSpec] = field(default_factory=list)

    @property
    def manifest_path(self) -> Path:
        return self.output_dir / MANIFEST


def frame_seed(root: int, index: int) -> int:
    """The seed of frame ``index``: ``SeedSequence(root).spawn(n)[index]``'s first 64-bit word, halved.

    Equal to ``int(np.random.SeedSequence(root, spawn_key=(index,)).generate_state(1, np.uint64)[0] >> 1)``;
    independent of the batch's size, so frame i keeps its seed when sweeps grow.
    """
    ss = np.random.SeedSequence(int(root), spawn_key=(int(index),))
    return int(ss.generate_state(1, np.uint64)[0] >> np.uint64(1))


def frame_split(seed: int, fractions=SPLIT_FRACTIONS) -> str:
    """The split of the frame with ``seed``: ``u = first 8 bytes of sha256(str(seed)) / 2^64``, uniform in
    [0, 1); ``train`` if u < f_train, ``val`` if u < f_train + f_val, else ``test``.

    A function of the seed alone: a frame keeps its split when the batch grows or is re-run, and the
    fractions are met in expectation (binomial scatter for a finite batch).
    """
    u = int.from_bytes(hashlib.sha256(str(int(seed)).encode()).digest()[:8], "big") / 2.0 ** 64
    f_train, f_val = float(fractions[0]), float(fractions[1])
    return "train" if u < f_train else ("val" if u < f_train + f_val else "test")


def _check_labels(formats, fractions, file: str, key: str) -> tuple[str, ...]:
    from scenes.app.bench.formats import FORMATS, parse_formats

    try:
        fmts = tuple(parse_formats(",".join(formats) if isinstance(formats, (list, tuple)) else formats))
    except ValueError as exc:
        raise SceneError(str(exc).partition(":")[0], key=key, file=file,
                         expected=f"one or more of {', '.join(FORMATS)}") from None
    if any(not (math.isfinite(f) and f >= 0) for f in fractions) or abs(sum(fractions) - 1.0) > 1e-9:
        raise SceneError(f"{list(fractions)} are not fractions summing to 1", key="batch.split", file=file,
                         expected="three fractions >= 0 (train, val, test) summing to 1")
    return fmts


def toml_inline(value: Any) -> str:
    """``value`` as an inline TOML value (what ``--set KEY=VALUE`` parses back to the same value)."""
    if isinstance(value, dict):
        return "{" + ", ".join(f"{_toml_key(k)} = {toml_inline(v)}" for k, v in value.items()) + "}"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_inline(v) for v in value) + "]"
    if isinstance(value, float) and math.isfinite(value):
        return repr(value)  # shortest round-trip form
    return tomli_w.dumps({"v": value}).partition(" = ")[2].rstrip("\n")


def _toml_key(key: str) -> str:
    return key if re.fullmatch(r"[A-Za-z0-9_-]+", key) else toml_inline(str(key))


def _flatten(table: dict, prefix: str = "") -> list[str]:
    """``[overrides]`` (nested tables from dotted TOML keys) -> ``--set`` strings; arrays replace whole."""
    out = []
    for k, v in table.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict) and v:
            out += _flatten(v, key + ".")
        else:
            out.append(f"{key}={toml_inline(v)}")
    return out


def _scene_path(name: str, base: Path) -> tuple[str, bytes]:
    """The scene argument as a worker sees it (absolute path or built-in name) and its content."""
    p = Path(name).expanduser()
    if not p.is_absolute():
        p = base / p
    if p.is_file():
        return str(p.resolve()), p.read_bytes()
    if (BUILTIN_SCENES / f"{name}.toml").is_file():
        return name, (BUILTIN_SCENES / f"{name}.toml").read_bytes()
    return str(p), b""


def _check_sweeps(sweeps: list[SweepCfg], file: str) -> None:
    """Each ``[[sweep]]``: dotted keys, each key swept once, values present (one list per point when zipped)."""
    seen = set()
    for i, sw in enumerate(sweeps):
        if not sw.keys:
            raise SceneError("an empty list of keys", key=f"sweep.{i}.key", file=file, expected="one or more keys")
        for k in sw.keys:
            if not _DOTTED.match(k):
                raise SceneError(f"{k!r} is not a dotted scene key", key=f"sweep.{i}.key", file=file,
                                 expected="a key like exposure.time_s")
            if k in seen:
                raise SceneError(f"{k!r} is swept twice", key=f"sweep.{i}.key", file=file,
                                 expected="each scene key in one [[sweep]] (list keys to vary them together)")
            seen.add(k)
        if not sw.values:
            raise SceneError("no values", key=f"sweep.{i}.values", file=file, expected="one value or more")
        if isinstance(sw.key, list):
            for j, v in enumerate(sw.values):
                if not isinstance(v, list) or len(v) != len(sw.key):
                    raise SceneError(f"{v!r} is not a list of {len(sw.key)} values", key=f"sweep.{i}.values[{j}]",
                                     file=file, expected=f"one value per key of {sw.key}")


def load_batch(path: str | os.PathLike, sets: list[str] | tuple[str, ...] = (),
               output_dir: str | os.PathLike | None = None, labels: str | list[str] | None = None) -> Batch:
    """Read and validate a batch file; check its base scene; list its frames.

    ``sets`` are ``--set`` overrides of the base scene (after the file's ``[overrides]``); ``output_dir``
    replaces ``[batch] output_dir``; ``labels`` (``"coco,yolo"``) replaces ``[batch] labels``. Raises :class:`SceneError` naming the file, the key and what was
    expected.
    """
    p = Path(path)
    file = str(p)
    if not p.is_file():
        raise SceneError("batch file not found", file=file, expected="a batch TOML file")
    try:
        data = tomllib.loads(p.read_text())
    except (tomllib.TOMLDecodeError, OSError, UnicodeDecodeError) as exc:
        raise SceneError(f"cannot read it as TOML ({exc})", file=file, expected="a TOML batch file") from None
    try:
        cfg = validate(BatchFile, data, file=file)
    except DetectorError as exc:
        raise SceneError(exc.message, key=exc.key, expected=exc.expected, file=file) from None
    scene, text = _scene_path(cfg.batch.scene, p.parent)
    if not text:
        raise SceneError(f"scene {scene!r} not found", key="batch.scene", file=file,
                         expected="a scene TOML path relative to the batch file, or a built-in scene")
    base_sets = _flatten(cfg.overrides) + list(sets)
    _check_sweeps(cfg.sweep, file)
    fmts = _check_labels(cfg.batch.labels if labels is None else labels, cfg.batch.split, file,
                         "batch.labels" if labels is None else "--labels")
    try:  # the base scene must be valid; a bad sweep value fails only its own frames
        load_scene(scene, base_sets)
    except DetectorError as exc:
        raise SceneError(f"base scene: {exc}", file=file) from None
    n_points = math.prod(len(sw.values) for sw in cfg.sweep)
    steps = cfg.sequence.frames if cfg.sequence else 1
    draws = cfg.montecarlo.draws if cfg.montecarlo else 1
    n = n_points * steps * draws
    if n > MAX_FRAMES:
        raise SceneError(f"the batch has {n} frames", key="sweep", file=file, expected=f"at most {MAX_FRAMES}")
    out = Path(output_dir or cfg.batch.output_dir or Path("out") / p.stem).expanduser().resolve()
    batch = Batch(file, cfg, scene, hashlib.sha256(text).hexdigest(), out)
    width = max(4, len(str(n - 1)))
    cadence = cfg.sequence.cadence_s if cfg.sequence else 0.0
    points = itertools.product(*(sw.points() for sw in cfg.sweep))
    for i_point, point in enumerate(points):
        overrides = {k: v for part in point for k, v in part.items()}
        point_sets = tuple(base_sets + [f"{k}={toml_inline(v)}" for k, v in overrides.items()])
        for k in range(steps):
            for d in range(draws):
                i = (i_point * steps + k) * draws + d
                seed = frame_seed(cfg.batch.seed, i)
                batch.frames.append(FrameSpec(
                    i, str(out / f"frame_{i:0{width}d}.fits"), scene, point_sets, overrides, k, cadence, d,
                    seed, cfg.batch.noiseless, cfg.batch.expected, cfg.batch.png, batch.scene_sha256, fmts,
                    frame_split(seed, cfg.batch.split)))
    return batch


# ------------------------------------------------------------------------------------------ sequences
def _advance(ra_deg: float, dec_deg: float, rate_ra: float, rate_dec: float, dt_s: float):
    """Move along the great circle tangent to the on-sky rates for ``dt_s``: new RA, Dec and rates.

    Rates are dRA/dt cos(Dec) and dDec/dt [deg/s] (the convention of ``[[objects]]`` and ``rate``
    tracking); the speed is kept and the rates are re-expressed in the new position's east/north.
    """
    p0 = radec_to_unit(ra_deg, dec_deg)
    east, north = east_north(p0)
    w = rate_ra * east + rate_dec * north
    speed = float(np.linalg.norm(w))
    if speed == 0.0:
        return ra_deg, dec_deg, rate_ra, rate_dec
    pole = np.cross(p0, w) / speed
    p = Boresight(ra_deg, dec_deg, "rate", rate_ra, rate_dec).unit(dt_s)[0]
    v = speed * np.cross(pole, p)
    e1, n1 = east_north(p)
    ra, dec = unit_to_radec(p)
    return float(ra), float(dec), float(v @ e1), float(v @ n1)


def sequence_overrides(scene: Scene, dt_s: float) -> dict[str, Any]:
    """The scene keys that change when the exposure starts ``dt_s`` later, the mount still tracking.

    ``pointing.epoch`` moves by ``dt_s``; a ``rate``-tracking boresight and every RA/Dec + rate object
    move on along their great circles (rates re-expressed at the new position); with ``tracking =
    "none"`` the boresight's RA grows at the sidereal rate; a ``sidereal`` mount keeps its RA/Dec. TLE
    objects follow from the epoch.
    """
    from astropy.time import Time, TimeDelta

    if dt_s == 0:
        return {}
    t = Time(scene.pointing.epoch, format="isot", scale="utc") + TimeDelta(dt_s, format="sec")
    t.precision = 6
    out: dict[str, Any] = {"pointing.epoch": t.isot}
    p, exp = scene.pointing, scene.exposure
    if exp.tracking == "rate":
        ra, dec, rra, rdec = _advance(p.ra_deg, p.dec_deg, exp.rate_ra_deg_s, exp.rate_dec_deg_s, dt_s)
        out.update({"pointing.ra_deg": ra, "pointing.dec_deg": dec, "exposure.rate_ra_deg_s": rra,
                    "exposure.rate_dec_deg_s": rdec})
    elif exp.tracking == "none":
        ra, _ = unit_to_radec(Boresight(p.ra_deg, p.dec_deg, "none").unit(dt_s)[0])
        out["pointing.ra_deg"] = float(ra)
    objects, moved = [], False
    for table in scene.objects:
        # an object may leave the field during a sequence: those frames are rendered without it (the base
        # scene, step 0, still refuses an object that never enters)
        table = {**table, "outside": table.get("outside", "skip")}
        moved = True
        if "ra_deg" in table and (table.get("rate_ra_deg_s") or table.get("rate_dec_deg_s")):
            ra, dec, rra, rdec = _advance(table["ra_deg"], table["dec_deg"], table.get("rate_ra_deg_s", 0.0),
                                          table.get("rate_dec_deg_s", 0.0), dt_s)
            table.update(ra_deg=ra, dec_deg=dec, rate_ra_deg_s=rra, rate_dec_deg_s=rdec)
            moved = True
        objects.append(table)
    if moved:
        out["objects"] = objects
    return out


def frame_sets(spec: FrameSpec) -> list[str]:
    """All ``--set`` overrides of a frame: the spec's, then its sequence step's (needs the scene)."""
    sets = list(spec.sets)
    if spec.step:
        scene = load_scene(spec.scene, sets)
        sets += [f"{k}={toml_inline(v)}" for k, v in sequence_overrides(scene, spec.step * spec.cadence_s).items()]
    return sets


def render_command(spec: FrameSpec, sets: list[str]) -> str:
    """The ``newtsim render`` command that writes the same bytes as the batch."""
    args = ["newtsim", "render", spec.scene, "-o", spec.file, "--seed", str(spec.seed), "--no-png"]
    args += ["--noiseless"] * spec.noiseless + ["--expected"] * spec.expected
    args += ["--labels", ",".join(spec.labels)] if spec.labels else []
    for s in sets:
        args += ["--set", s]
    return shlex.join(args)


# ------------------------------------------------------------------------------------------ the task
def _sha256(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 22), b""):
            h.update(chunk)
    return h.hexdigest()


def label_files(spec: FrameSpec) -> dict[str, Path]:
    """A frame's label files (format -> path), named as ``render --labels`` names them."""
    ext = {"coco": ".coco.json", "satnet": ".satnet.json", "yolo": ".yolo.txt"}
    p = Path(spec.file)
    return {f: p.with_name(p.stem + ext[f]) for f in spec.labels if f in ext}


def render_frame(spec: FrameSpec) -> dict:
    """Render one frame (the Dask task). Never raises: a failure is returned as ``status = "failed"``.

    The render runs on one thread (``workers=1``): the cluster's workers are the parallelism. The FITS
    file is written under a temporary name and renamed when complete; an older file of the same name is
    removed first, so a file on disk always belongs to its manifest entry.
    """
    from optics.design import OpticsError

    t0 = time.perf_counter()
    res: dict[str, Any] = {"index": spec.index, "status": "failed", "host": socket.gethostname(), "pid": os.getpid()}
    tmps: dict[str, Path] = {}
    try:
        Path(spec.file).unlink(missing_ok=True)
        sets = frame_sets(spec)
        res["set"] = sets
        res["command"] = render_command(spec, sets)
        scene = load_scene(spec.scene, sets)
        finals = label_files(spec)
        for f in finals.values():
            f.unlink(missing_ok=True)
        tmps = {fmt: f.with_name(f".{f.name}.{os.getpid()}.{uuid.uuid4().hex[:6]}.part") for fmt, f in finals.items()}
        meta = {"scene": spec.scene, "index": spec.index, "split": spec.split}
        summary = render(scene, spec.file, seed=spec.seed, noiseless=spec.noiseless, expected=spec.expected,
                         progress=False, workers=1, labels=list(spec.labels), label_paths=tmps, label_meta=meta)
        for fmt, tmp in tmps.items():
            os.replace(tmp, finals[fmt])
        if spec.labels:
            res["labels"] = {"count": summary.get("labels", 0), "files": {k: v.name for k, v in finals.items()}}
        if spec.png:
            png = Path(spec.file).with_suffix(".png")
            tmp = png.with_name(f".{png.stem}.{os.getpid()}.tmp.png")
            write_png(spec.file, tmp)
            os.replace(tmp, png)
        res.update(status="done", sha256=_sha256(spec.file), bytes=os.path.getsize(spec.file),
                   warnings=summary["warnings"])
    except (DetectorError, OpticsError) as exc:
        res["error"] = str(exc)
    except Exception as exc:  # noqa: BLE001 -- an unexpected failure is still one frame's: kept with its traceback
        res["error"] = f"{type(exc).__name__}: {exc}"
        res["traceback"] = traceback.format_exc()
    finally:
        for tmp in tmps.values():
            tmp.unlink(missing_ok=True)
    res["wall_s"] = round(time.perf_counter() - t0, 4)
    return res


# ------------------------------------------------------------------------------------------ manifest
def _entry(spec: FrameSpec, status: str = "pending") -> dict:
    return {"index": spec.index, "file": Path(spec.file).name, "scene": spec.scene, "overrides": spec.overrides,
            "step": spec.step, "draw": spec.draw, "seed": spec.seed, "split": spec.split, "status": status,
            "spec_sha256": spec.spec_sha256}


def _read_manifest(path: Path) -> dict[int, dict]:
    """Entries of an existing manifest by index ({} if absent or unreadable: those frames are re-rendered)."""
    try:
        data = json.loads(path.read_text())
        return {int(e["index"]): e for e in data.get("frames", [])}
    except (OSError, ValueError, TypeError, KeyError, AttributeError):
        return {}


def _is_done(spec: FrameSpec, entry: dict | None) -> bool:
    if not entry or entry.get("status") != "done" or entry.get("spec_sha256") != spec.spec_sha256:
        return False
    p = Path(spec.file)
    return p.is_file() and p.stat().st_size == entry.get("bytes") and all(f.is_file() for f in label_files(spec).values())


def plan(batch: Batch, force: bool = False) -> tuple[list[FrameSpec], dict[int, dict]]:
    """The frames to render and the manifest entries (done frames kept, the others pending)."""
    old = {} if force else _read_manifest(batch.manifest_path)
    todo, entries = [], {}
    for spec in batch.frames:
        if _is_done(spec, old.get(spec.index)):
            entries[spec.index] = old[spec.index]
        else:
            todo.append(spec)
            entries[spec.index] = _entry(spec)
    return todo, entries


def _write_manifest(batch: Batch, entries: dict[int, dict]) -> None:
    b = batch.cfg.batch
    data = {"manifest_version": MANIFEST_VERSION, "batch_file": str(Path(batch.path).resolve()),
            "scene": batch.scene, "scene_sha256": batch.scene_sha256, "root_seed": b.seed,
            "output_dir": str(batch.output_dir), "noiseless": b.noiseless, "expected": b.expected,
            "frames_total": len(batch.frames),
            "split": {"fractions": dict(zip(SPLITS, b.split)),
                      "rule": "u = int(sha256(str(seed))[:8 bytes], big-endian) / 2^64: train if u < f_train, "
                              "val if u < f_train + f_val, else test"},
            "labels": _labels_info(batch),
            "counts": {s: sum(e["status"] == s for e in entries.values()) for s in ("done", "failed", "pending")},
            "updated": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "frames": [entries[i] for i in sorted(entries)]}
    tmp = batch.manifest_path.with_name(f".{MANIFEST}.{os.getpid()}.part")
    tmp.write_text(json.dumps(jsonable(data), indent=1, allow_nan=False, default=str) + "\n")
    os.replace(tmp, batch.manifest_path)


def _labels_info(batch: Batch) -> dict | None:
    fmts = batch.frames[0].labels if batch.frames else ()
    if not fmts:
        return None
    from scenes.app.bench.labels import MASK_FRACTION_SIGMA, label_rule

    return {"formats": list(fmts), "dataset_files": {f: DATASET_FILES[f] for f in fmts if f in DATASET_FILES},
            "split_lists": [f"{s}.txt" for s in SPLITS], "label_rule": label_rule(MASK_FRACTION_SIGMA)}


def _write_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.part")
    tmp.write_text(text)
    os.replace(tmp, path)


def write_dataset(batch: Batch, entries: dict[int, dict]) -> dict[str, str]:
    """The dataset files of a labelled batch from the label files of its frames that are done.

    ``dataset.coco.json``: every frame's COCO image with id = frame index + 1 (stable when the batch grows)
    and its annotations renumbered 1..N; ``dataset.satnet.json``: the list of the frames' SatNet entries;
    ``train.txt``, ``val.txt``, ``test.txt``: the frame files of each split. Returns format -> path.
    """
    fmts = batch.frames[0].labels if batch.frames else ()
    if not fmts:
        return {}
    done = [s for s in batch.frames if entries.get(s.index, {}).get("status") == "done"]
    out = {}
    if "coco" in fmts:
        images, anns, info, cats = [], [], None, []
        for spec in done:
            doc = json.loads(label_files(spec)["coco"].read_text())
            info, cats = info or doc["info"], cats or doc["categories"]
            for img in doc["images"]:
                old = img["id"]
                img = {**img, "id": spec.index + 1}
                images.append(img)
                for a in doc["annotations"]:
                    if a["image_id"] == old:
                        anns.append({**a, "image_id": img["id"], "id": len(anns) + 1})
        doc = {"info": {**(info or {"description": "newtsim labels"}), "frames": len(images)},
               "images": images, "annotations": anns, "categories": cats}
        out["coco"] = batch.output_dir / DATASET_FILES["coco"]
        _write_atomic(out["coco"], json.dumps(doc, indent=1, allow_nan=False))
    if "satnet" in fmts:
        frames = [json.loads(label_files(spec)["satnet"].read_text()) for spec in done]
        out["satnet"] = batch.output_dir / DATASET_FILES["satnet"]
        _write_atomic(out["satnet"], json.dumps(frames, indent=1, allow_nan=False))
    for split in SPLITS:
        _write_atomic(batch.output_dir / f"{split}.txt",
                      "".join(f"{Path(s.file).name}\n" for s in done if s.split == split))
    return {k: str(v) for k, v in out.items()}


def _remove_stale_parts(folder: Path) -> int:
    """Temporary files of frames whose render was killed (one batch per output folder at a time)."""
    n = 0
    for p in folder.glob(".frame_*.part"):
        p.unlink(missing_ok=True)
        n += 1
    for p in folder.glob(".frame_*.tmp.png"):
        p.unlink(missing_ok=True)
    for p in folder.glob(".dataset.*.part"):
        p.unlink(missing_ok=True)
    return n


# ------------------------------------------------------------------------------------------ running
def local_workers() -> int:
    """Cores available to this process."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def _connect(scheduler: str | None, workers: int | None, processes: bool):
    """A Dask client: to ``scheduler`` (an address or a scheduler JSON file), or to a new LocalCluster."""
    from distributed import Client, LocalCluster

    if scheduler:
        try:
            if Path(scheduler).is_file():
                return Client(scheduler_file=scheduler, timeout="20s"), None
            return Client(scheduler, timeout="20s"), None
        except (OSError, TimeoutError, ValueError) as exc:
            raise SceneError(f"cannot reach the Dask scheduler ({exc})", key="--scheduler",
                             expected="a running scheduler's address (tcp://HOST:8786) or its scheduler file") from None
    cluster = LocalCluster(n_workers=workers or local_workers(), threads_per_worker=1, processes=processes,
                           dashboard_address=None, silence_logs=logging.ERROR)
    return Client(cluster), cluster


class _Reporter:
    """Progress on stderr: a rich bar on a terminal, one line per frame otherwise."""

    def __init__(self, total: int, enabled: bool):
        self.total, self.done, self.failed = total, 0, 0
        self.bar = self.task = None
        self.lines = enabled and not sys.stderr.isatty()
        if enabled and sys.stderr.isatty():
            from rich.console import Console
            from rich.progress import (
                BarColumn,
                MofNCompleteColumn,
                Progress,
                TextColumn,
                TimeElapsedColumn,
                TimeRemainingColumn,
            )

            self.bar = Progress(TextColumn("[bold]batch[/bold]"), BarColumn(), MofNCompleteColumn(),
                                TextColumn("{task.fields[failed]} failed"), TimeElapsedColumn(),
                                TimeRemainingColumn(), console=Console(stderr=True), transient=True)
            self.task = self.bar.add_task("frames", total=total, failed=0)
            self.bar.start()

    def update(self, res: dict, name: str) -> None:
        self.done += 1
        self.failed += res["status"] != "done"
        if self.bar is not None:
            self.bar.update(self.task, advance=1, failed=self.failed)
        elif self.lines:
            what = "done" if res["status"] == "done" else f"FAILED: {res.get('error', '')}"
            print(f"[{self.done}/{self.total}] {name} {what} ({res.get('wall_s', 0):.2f} s)", file=sys.stderr,
                  flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.stop()


def run_batch(batch: Batch, *, scheduler: str | None = None, workers: int | None = None, processes: bool = True,
              force: bool = False, progress: bool = True, client=None) -> dict:
    """Render the frames of ``batch`` that are not done yet, on Dask; return a summary.

    Parameters
    ----------
    scheduler : a Dask scheduler's address or scheduler file; default a LocalCluster on this machine
    workers : LocalCluster worker processes (default: the cores), one thread each
    processes : LocalCluster workers as processes (default) or threads
    force : re-render frames that are done
    client : an existing ``distributed.Client`` (overrides ``scheduler``/``workers``)

    Returns a dict: ``frames``, ``rendered``, ``skipped``, ``failed`` (counts), ``failures`` (index, file,
    overrides, error), ``manifest``, ``output_dir``, ``scheduler``, ``wall_s``.
    """
    t0 = time.perf_counter()
    batch.output_dir.mkdir(parents=True, exist_ok=True)
    _remove_stale_parts(batch.output_dir)
    todo, entries = plan(batch, force)
    _write_manifest(batch, entries)
    summary = {"frames": len(batch.frames), "skipped": len(batch.frames) - len(todo), "rendered": 0, "failed": 0,
               "failures": [], "manifest": str(batch.manifest_path), "output_dir": str(batch.output_dir),
               "scheduler": None}
    if todo:
        own = client is None
        cluster = None
        if own:
            client, cluster = _connect(scheduler, workers, processes)
        summary["scheduler"] = client.scheduler.address
        try:
            _run(client, batch, todo, entries, summary, progress)
        finally:
            if own:
                client.close()
                if cluster is not None:
                    cluster.close()
    if batch.frames and batch.frames[0].labels:
        summary["dataset"] = write_dataset(batch, entries)
    summary["wall_s"] = round(time.perf_counter() - t0, 3)
    return summary


def _run(client, batch: Batch, todo: list[FrameSpec], entries: dict[int, dict], summary: dict,
         progress: bool) -> None:
    from distributed import as_completed

    run = uuid.uuid4().hex[:8]
    futures = {client.submit(render_frame, s, key=f"newtsim-frame-{s.index}-{run}", pure=False): s for s in todo}
    rep = _Reporter(len(todo), progress)
    last_save = time.monotonic()
    try:
        for fut in as_completed(futures):
            spec = futures[fut]
            try:
                res = fut.result()
            except Exception as exc:  # noqa: BLE001 -- the worker died (memory, killed): that frame failed
                res = {"index": spec.index, "status": "failed", "error": f"{type(exc).__name__}: {exc}"}
            entries[spec.index] = {**_entry(spec, res["status"]), **{k: v for k, v in res.items() if k != "index"}}
            if res["status"] == "done":
                summary["rendered"] += 1
            else:
                summary["failed"] += 1
                summary["failures"].append({"index": spec.index, "file": Path(spec.file).name,
                                            "overrides": spec.overrides, "error": res.get("error", "")})
            rep.update(res, Path(spec.file).name)
            if time.monotonic() - last_save >= _SAVE_EVERY_S:
                _write_manifest(batch, entries)
                last_save = time.monotonic()
    except BaseException:
        client.cancel(list(futures))
        raise
    finally:
        rep.close()
        _write_manifest(batch, entries)
    summary["failures"].sort(key=lambda f: f["index"])

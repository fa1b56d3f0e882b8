"""``newtsim demo``: the product in two steps, for a newcomer (``make demo``).

1. :func:`showcase_frame` renders the built-in scene ``showcase`` (``scenes/data/showcase.toml``: the full
   IMX411 frame behind the ART optics, catalogue stars, a debris streak, ray-traced vignetting, distortion
   and PSF, the detector effects of a real camera) to a FITS frame and a quick-look PNG with zoomed insets
   on the streak and on a bright isolated star (:func:`scenes.app.quicklook.write_png_insets`).
2. :func:`hidden_effect_round` makes a "measured" frame of a window of the same scene with one physical
   effect the scene lacks (by default a sky-brightness gradient, as scattered moonlight makes), a
   different noise and cosmic-ray draw, and runs one compare / diagnose / ``--apply`` / compare round on
   it (:func:`scenes.app.compare.diagnose_round`, :func:`scenes.app.compare.run_compare`): the diagnosis
   names the effect and the error (chi2/dof) falls once the fitted effect is in the scene.

Everything is written into one folder; :func:`run_demo` runs both and returns the summary lines that the
command prints (and the README quotes).
"""

from __future__ import annotations

import copy
import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import tomli_w
import tomllib
from astropy.io import fits

from detector.jsonable import jsonable
from scenes.errors import SceneError
from scenes.scene import BUILTIN_SCENES, load_scene

from .compare import diagnose_round, run_compare
from .compare.report import write_report
from .quicklook import Inset, star_inset, streak_inset, write_png_insets
from .render import render

#: the built-in scene the demo renders
SHOWCASE = "showcase"

Log = Callable[[str], None]


def _quiet(_: str) -> None:
    return None


@dataclass
class HiddenRound:
    """The compare / diagnose round of the demo: a window of the showcase with one effect hidden in it.

    Attributes
    ----------
    width, height : window size [pixels]
    centre_x, centre_y : window centre on the sensor [pixels]; None: the sensor's centre (the optical axis),
        where the showcase's streak passes ~100 px away, so the window holds stars and a stretch of streak
    hidden : the effect the "measured" frame has and the scene lacks (a catalogue name)
    params : its parameters. The default is a sky gradient (``sky_gradient``: a plane of e-/s per pixel
        about the sensor's centre, as scattered moonlight or twilight makes) of 10 e-/s per pixel per 1000
        pixels rising towards the upper left: +-25 % of the scene's 20 e-/s sky at the corners of a
        1024-pixel window, about 1 sigma of a pixel's noise there. About the sensor's centre the plane adds
        no mean light to the window, so the error it makes is its shape, not a sky level.
    seed : the frame seed of the measured frame (the model scene keeps its own: another noise and
        cosmic-ray draw)
    """

    width: int = 1024
    height: int = 1024
    centre_x: int | None = None
    centre_y: int | None = None
    hidden: str = "sky_gradient"
    params: dict = field(default_factory=lambda: {"gx_e_per_s_per_kpx": -8.0, "gy_e_per_s_per_kpx": 6.0})
    seed: int = 20231

    def window(self, sensor_width_px: int, sensor_height_px: int) -> dict:
        """The ``[detector]`` window keys (x0, y0: the lower-left corner on the sensor)."""
        cx = self.centre_x if self.centre_x is not None else sensor_width_px // 2
        cy = self.centre_y if self.centre_y is not None else sensor_height_px // 2
        return {"width": self.width, "height": self.height,
                "x0": int(cx - self.width // 2), "y0": int(cy - self.height // 2)}


def scene_table(name: str = SHOWCASE) -> dict:
    """A built-in scene as a table (to derive the demo's scenes from)."""
    return tomllib.loads((BUILTIN_SCENES / f"{name}.toml").read_text())


def _write(table: dict, path: Path, comment: str = "") -> Path:
    head = "".join(f"# {line}\n" for line in comment.splitlines())
    path.write_text(head + tomli_w.dumps(table))
    return path


def insets_for(fits_path: str | Path) -> list[Inset]:
    """The quick-look's insets: the streak (TRUTH ``kind == object``) and a bright isolated unsaturated star."""
    with fits.open(fits_path, memmap=True) as h:
        truth = h["TRUTH"].data if "TRUTH" in h else None
        shape = (h[0].header["NAXIS2"], h[0].header["NAXIS1"])
        full_well = h[0].header.get("FULLWELL")
        truth = None if truth is None else truth.copy()
    streak = streak_inset(truth, shape, at=0.4)
    # total electrons below 2 full wells: the PSF's peak pixel (< 25 % of the light) stays unsaturated
    star = star_inset(truth, shape, half_px=20, saturation_e=2.0 * full_well if full_well else None, avoid=streak)
    return [i for i in (streak, star) if i is not None]


def showcase_frame(out_dir: str | Path, scene: str = SHOWCASE, overrides: list[str] | None = None,
                   workers: int | None = None) -> dict:
    """Render ``scene`` to ``OUT/demo.fits`` and its quick-look with insets to ``OUT/demo.png``."""
    out = Path(out_dir)
    sc = load_scene(scene, overrides or [])
    t0 = time.perf_counter()
    summary = render(sc, out / "demo.fits", workers=workers)
    t1 = time.perf_counter()
    insets = insets_for(out / "demo.fits")
    s = sc.sensor()
    title = (f"newtsim showcase: {s.output_shape[1]}x{s.output_shape[0]} IMX411 behind the ART 40 cm f/2.4, "
             f"{sc.exposure.time_s:g} s, {summary['sources']['stars']} stars, 1 debris streak (block-averaged)")
    png = write_png_insets(out / "demo.fits", out / "demo.png", insets, title=title)
    summary.update(png=str(png), insets=[vars(i) for i in insets],
                   seconds={"render": t1 - t0, "png": time.perf_counter() - t1})
    return summary


def round_window(cfg: HiddenRound, scene: str = SHOWCASE) -> dict:
    """The round's ``[detector]`` window on the scene's sensor, checked (a :class:`scenes.errors.SceneError`
    naming the key when it does not fit the sensor, or when the scene already has the hidden effect)."""
    full = load_scene(scene).sensor()
    window = cfg.window(full.sensor_width_px, full.sensor_height_px)
    sc = load_scene(scene, [f"detector.{k}={v}" for k, v in window.items()])
    if cfg.hidden in sc.effects:
        raise SceneError(f"the scene already has [effects.{cfg.hidden}]: nothing would be hidden",
                         key=f"effects.{cfg.hidden}", file=sc.source)
    return window


def hidden_effect_round(out_dir: str | Path, cfg: HiddenRound | None = None, scene: str = SHOWCASE,
                        workers: int | None = None, log: Log = _quiet) -> dict:
    """One compare / diagnose / apply / compare round on a window of ``scene`` with ``cfg.hidden`` hidden.

    Writes into ``out_dir``: ``round_model.toml`` (the window of the scene), ``round_measured.toml`` and
    ``round_measured.fits`` (the window with the hidden effect, another seed), ``round_diagnosis.json``,
    ``round_report.html``, ``round_applied.toml`` (the scene with the named effect, fitted parameters
    included) and the ledger (``round_applied.ledger.json`` / ``.png``). Returns a summary: the hidden effect,
    the ranking, chi2/dof before and after, and the files.
    """
    cfg = cfg or HiddenRound()
    out = Path(out_dir)
    base = scene_table(scene)
    window = round_window(cfg, scene)
    base["detector"] = {**base["detector"], **window}
    model_path = _write(base, out / "round_model.toml",
                        f"newtsim demo: the model scene, a {cfg.width}x{cfg.height} window of the built-in '{scene}'")
    measured = copy.deepcopy(base)
    measured.setdefault("effects", {})[cfg.hidden] = dict(cfg.params)
    measured_path = _write(measured, out / "round_measured.toml",
                           f"newtsim demo: what the 'measured' frame round_measured.fits was rendered from (seed "
                           f"{cfg.seed}):\nthe model scene round_model.toml plus [effects.{cfg.hidden}], which the "
                           "model lacks")
    t = {}
    t0 = time.perf_counter()
    log(f"rendering the measured frame: a {cfg.width}x{cfg.height} window with [effects.{cfg.hidden}] "
        f"{cfg.params}, seed {cfg.seed}")
    render(load_scene(str(measured_path)), out / "round_measured.fits", seed=cfg.seed, workers=workers,
           progress=False)
    t["measure"] = time.perf_counter() - t0
    log("diagnosing: every effect the scene lacks fitted to the residuals, ranked by delta BIC")
    t0 = time.perf_counter()
    applied_path = out / "round_applied.toml"
    for stale in (applied_path, out / "round_applied.ledger.json", out / "round_model.ledger.json"):
        stale.unlink(missing_ok=True)
    diag = diagnose_round(load_scene(str(model_path)), model_path, out / "round_measured.fits",
                          apply_to=applied_path, workers=workers)
    cmp_before = diag.pop("_compare")
    write_report(cmp_before, out / "round_report.html", diagnosis=diag,
                 title=f"newtsim demo: diagnosis of a frame with {cfg.hidden} hidden")
    t["diagnose"] = time.perf_counter() - t0
    before = diag["baseline"]["chi2_per_dof"]
    cands = diag["candidates"]
    first = cands[0] if cands else None  # ranked best first; the first is the verdict's when significant
    after = None
    if diag["applied"]:
        log(f"comparing the applied scene ({applied_path.name}) with the measured frame")
        t0 = time.perf_counter()
        cmp_after = run_compare(load_scene(str(applied_path)), out / "round_measured.fits", workers=workers)
        after = cmp_after["summary"]["chi2_per_dof"]
        write_report(cmp_after, out / "round_applied_report.html",
                     title=f"newtsim demo: the applied scene (+{diag['applied']['effect']}) vs the measured frame")
        t["compare_after"] = time.perf_counter() - t0
    result = {
        "hidden": cfg.hidden, "hidden_params": cfg.params, "window": window, "seed": cfg.seed,
        "named_first": first["effect"] if first else None,
        "named_first_significant": bool(first and first["significant"]),
        "delta_bic": first["delta_bic"] if first else None,
        "fitted_params": first["params"] if first else None,
        "explanation": first["explanation"] if first else diag["verdict"],
        "ranking": [(c["effect"], c["delta_bic"]) for c in cands[:6]],
        "verdict": diag["verdict"], "applied": diag["applied"],
        "chi2_per_dof_before": before, "chi2_per_dof_after": after, "seconds": t,
        "files": {"model_scene": str(model_path), "measured_scene": str(measured_path),
                  "measured": str(out / "round_measured.fits"), "diagnosis": str(out / "round_diagnosis.json"),
                  "report": str(out / "round_report.html"),
                  "applied_scene": str(applied_path) if diag["applied"] else None,
                  "applied_report": str(out / "round_applied_report.html") if after is not None else None},
    }
    (out / "round_diagnosis.json").write_text(json.dumps(jsonable(
        {"demo": {k: v for k, v in result.items() if k != "files"}, "baseline": diag["baseline"],
         "candidates": diag["candidates"], "verdict": diag["verdict"], "problems": diag["problems"],
         "applied": diag["applied"], "ledger": diag["ledger"]}), indent=1, default=str) + "\n")
    return result


def _fmt_params(params: dict) -> str:
    return ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in params.items())


def _stars_words(src: dict) -> str:
    """The stars on the frame, split into catalogue (Gaia) stars and faint-star model stars when known."""
    if "catalogue_stars" not in src:
        return f"{src['stars']} stars"
    return f"{src['stars']} stars ({src['catalogue_stars']} Gaia catalogue, {src['model_stars']} faint-star model)"


def summary_lines(frame: dict | None, rnd: dict | None) -> list[str]:
    """The lines the demo prints (and the README quotes)."""
    lines = []
    if frame is not None:
        h, w = frame["shape"]
        lines.append(f"rendered {frame['path']}: {w}x{h} px, {frame['exptime_s']:g} s, "
                     f"{_stars_words(frame['sources'])}, {frame['sources']['objects']} debris streak; "
                     f"quick-look {frame['png']}")
    if rnd is not None:
        lines.append(f"hidden in the measured frame: {rnd['hidden']} ({_fmt_params(rnd['hidden_params'])})")
        if rnd["named_first"] is None or not rnd["named_first_significant"]:
            lines.append("diagnose names: no significant missing effect")
        else:
            lines.append(f"diagnose names: {rnd['named_first']} (delta BIC {rnd['delta_bic']:,.0f}; "
                         f"fitted {_fmt_params(rnd['fitted_params'])})")
        after = rnd["chi2_per_dof_after"]
        lines.append(f"chi2/dof {rnd['chi2_per_dof_before']:.2f} -> "
                     + (f"{after:.2f} after --apply" if after is not None else "(nothing applied)"))
    return lines


def run_demo(out_dir: str | Path = "out", *, frame: bool = True, cfg: HiddenRound | None = None,
             workers: int | None = None, log: Log = _quiet) -> dict:
    """Both steps of the demo into ``out_dir``; returns ``{"frame", "round", "lines", "seconds"}``."""
    round_window(cfg or HiddenRound())  # a window that does not fit fails now, not after the frame
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    shown = None
    if frame:
        log("rendering the built-in scene 'showcase' (full frame; the optics are ray-traced once and cached)")
        shown = showcase_frame(out, workers=workers)
    t1 = time.perf_counter()
    rnd = hidden_effect_round(out, cfg, workers=workers, log=log)
    t2 = time.perf_counter()
    return {"frame": shown, "round": rnd, "lines": summary_lines(shown, rnd),
            "seconds": {"frame": t1 - t0, "round": t2 - t1, "total": t2 - t0}}

"""Design optimisation: the field corrector (gradients) and the baffle (derivative-free, common random numbers).

Corrector (:func:`optimize_corrector`)
    Minimise the polychromatic RMS spot radius over a grid of field points and a weighted band, varying
    every curved surface's radius and the glass and air thicknesses of the lens stack (the first surface
    stays where it is, so the corrector keeps its room in the focuser and the back focus takes up the
    change; the sensor stays at the design's focus). Residuals r_j = rms_j for each field point j plus a
    one-sided penalty w * max(0, rms_j - (1 - margin) rms0_j) that keeps every field point better than
    the start by a margin (1 %: room for the difference between the optimiser's and the check's samples); scipy's trust-region reflective least squares (``least_squares(method="trf")``, Branch,
    Coleman & Li 1999, doi:10.1137/S1064827595289108) with the Jacobian from drjit's AD
    (:func:`optics.gradients.spot_moments`), bounded radii (+-``radius_frac``) and thicknesses
    (+-``thickness_mm``, glass >= 3 mm, air >= 1 mm). The same pupil points serve every iteration
    (common random numbers): the objective is smooth and deterministic. The result is checked with an
    independent pupil sample (another seed, more rays) and validated as a design (lens edges, room).

Baffle (:func:`optimize_baffle`)
    Minimise the mean log10 PST at the given off-axis angles (Sun angles) over the vanes' number, the
    height of the lowest vane (``zone_start_mm``; the vanes are spread evenly from there to the tube
    front) and their inner diameter, under the constraint that the relative illumination at the sensor's
    corner stays within ``max_corner_change`` (1 %) of the start's. The PST is a Monte Carlo estimate
    (:func:`optics.straylight.pst_curve`) whose gradient through the vane geometry is not reliable, so the
    search is derivative-free: a coordinate (compass) search, each candidate estimated with the same seed
    as the incumbent (common random numbers: the difference of two designs' PST has a far smaller error
    than either), a step halved when no move along any coordinate improves. The winner and the start are
    then re-estimated with an independent seed and more rays for the reported before/after.

Optics never imports ``detector``: the band's wavelengths and weights are the caller's.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from .design import Design, OpticsError
from .gradients import detector_field_points, spot_moments
from .sequential import SequentialTracer, pupil_uniform


# ---- corrector -----------------------------------------------------------------------------------------
def _corrector_variables(design: Design) -> list[str]:
    c = design.corrector
    names = [f"corrector.surfaces.{i}.radius_mm" for i, s in enumerate(c.surfaces) if s.radius_mm]
    names += [f"corrector.surfaces.{i}.thickness_mm" for i in range(len(c.surfaces) - 1)]
    return names


def _with_values(design: Design, values: dict) -> Design:
    """A copy of ``design`` with corrector radii/thicknesses replaced; the back focus absorbs the change of
    the stack's length (first surface fixed)."""
    data = design.model_dump()
    srf = data["corrector"]["surfaces"]
    old_len = sum(s["thickness_mm"] for s in srf[:-1])
    for name, v in values.items():
        _, _, i, key = name.split(".")
        srf[int(i)][key] = float(v)
    new_len = sum(s["thickness_mm"] for s in srf[:-1])
    data["corrector"]["back_focus_mm"] = float(data["corrector"]["back_focus_mm"] - (new_len - old_len))
    return Design.model_validate(data)


def rms_spots(tracer: SequentialTracer, fields, wavelengths_nm, weights, n_rays: int, seed: int = 0) -> np.ndarray:
    """Polychromatic RMS spot radius [mm] at each field point (hard edges: the plain trace's numbers)."""
    out = []
    px, py = pupil_uniform(n_rays, tracer.layout.r_primary, seed=seed)
    lam = np.asarray(wavelengths_nm, float)
    w = np.asarray(weights, float) / np.sum(weights)
    for f in fields:
        us, vs, ws = [], [], []
        for lk, wk in zip(lam, w):
            r = tracer.trace(tuple(f), px, py, float(lk))
            ok = r.ok
            us.append(r.u[ok])
            vs.append(r.v[ok])
            ws.append(r.transmission[ok] * wk)
        u, v, ww = np.concatenate(us), np.concatenate(vs), np.concatenate(ws)
        cu, cv = np.average(u, weights=ww), np.average(v, weights=ww)
        out.append(math.sqrt(np.average((u - cu) ** 2 + (v - cv) ** 2, weights=ww)))
    return np.asarray(out)


@dataclass
class CorrectorResult:
    design: Design
    fields_deg: np.ndarray
    rms_before_um: np.ndarray
    rms_after_um: np.ndarray
    variables: dict
    iterations: int
    seconds: float
    history: list = field(default_factory=list)

    def to_json(self) -> dict:
        b, a = self.rms_before_um, self.rms_after_um
        return {"goal": "corrector", "fields_deg": self.fields_deg.round(4).tolist(),
                "rms_spot_radius_um_before": b.round(3).tolist(), "rms_spot_radius_um_after": a.round(3).tolist(),
                "mean_before_um": round(float(b.mean()), 3), "mean_after_um": round(float(a.mean()), 3),
                "worst_change_um": round(float((a - b).max()), 3), "no_worse_everywhere": bool(np.all(a <= b + 1e-9)),
                "variables": {k: [round(v0, 4), round(v1, 4)] for k, (v0, v1) in self.variables.items()},
                "back_focus_mm": self.design.corrector.back_focus_mm, "iterations": self.iterations,
                "seconds": round(self.seconds, 2), "history_mean_rms_um": [round(h, 4) for h in self.history]}


def optimize_corrector(design: Design, mi, wavelengths_nm=(550.0,), weights=None, *, grid: int = 3,
                       n_rays: int = 1500, max_iter: int = 30, radius_frac: float = 0.03,
                       thickness_mm: float = 3.0, penalty: float = 100.0, margin: float = 0.01, verify_rays: int = 6000,
                       seed: int = 0, progress=None) -> CorrectorResult:
    """Optimise ``design``'s corrector for the smallest RMS spot over a ``grid`` x ``grid`` field and the
    band (module docstring). Returns the new design and the before/after RMS spot radii [um] from an
    independent check (``verify_rays`` rays per field and wavelength, seed ``seed + 1``)."""
    from scipy.optimize import least_squares

    if not design.corrector.enabled:
        raise OpticsError(f"optimize --goal corrector: design '{design.name}' has no corrector "
                          "(corrector.enabled = false)")
    t0 = time.perf_counter()
    lam = list(np.atleast_1d(np.asarray(wavelengths_nm, float)))
    wts = list(np.ones(len(lam)) if weights is None else np.asarray(weights, float))
    fields = detector_field_points(design, grid)
    names = _corrector_variables(design)
    wrt = tuple(names) + ("corrector.back_focus_mm",)
    tracer = SequentialTracer(design, mi)
    from .gradients import parameter_value

    x0 = np.array([parameter_value(design, n) for n in names])
    lo, hi = np.empty_like(x0), np.empty_like(x0)
    for k, n in enumerate(names):
        if n.endswith("radius_mm"):
            d = abs(x0[k]) * radius_frac
        else:
            d = thickness_mm
        lo[k], hi[k] = x0[k] - d, x0[k] + d
        if n.endswith("thickness_mm"):
            i = int(n.split(".")[2])
            glass = design.corrector.surfaces[i].material.lower() != "air"
            lo[k] = max(lo[k], 3.0 if glass else 1.0)
            hi[k] = max(hi[k], lo[k] + 1e-6)
    thick = np.array([n.endswith("thickness_mm") for n in names])
    bf0 = design.corrector.back_focus_mm
    len0 = x0[thick].sum()
    cache = {}

    def evaluate(x):
        key = x.tobytes()
        if key not in cache:
            at = dict(zip(names, x))
            at["corrector.back_focus_mm"] = bf0 - (x[thick].sum() - len0)
            m = spot_moments(tracer, fields, wrt, at=at, n_rays=n_rays, wavelengths_nm=lam, weights=wts, seed=seed)
            rms = m.get("rms_mm")
            J = m.jacobian[:, 5, :]                       # d rms / d (names..., back focus)
            Jx = J[:, :-1].copy()
            Jx[:, thick] -= J[:, -1:]                     # the back focus takes up the stack's length
            cache.clear()
            cache[key] = (rms, Jx)
        return cache[key]

    rms0 = evaluate(x0)[0].copy()
    target = rms0 * (1.0 - margin)      # the penalty starts ``margin`` below the start: room for sampling
    history = [float(rms0.mean() * 1e3)]

    def fun(x):
        rms, _ = evaluate(x)
        over = np.maximum(rms - target, 0.0)
        history.append(float(rms.mean() * 1e3))
        if progress:
            progress(len(history), max_iter + 1)
        return np.concatenate([rms, penalty * over]) / rms0.mean()

    def jac(x):
        rms, Jx = evaluate(x)
        over = (rms > target)[:, None]
        return np.vstack([Jx, penalty * Jx * over]) / rms0.mean()

    sol = least_squares(fun, x0, jac=jac, bounds=(lo, hi), method="trf", x_scale="jac", max_nfev=max_iter,
                        xtol=1e-10, ftol=1e-8)
    best = dict(zip(names, sol.x))
    from pydantic import ValidationError

    try:
        new = _with_values(design, best)
    except ValidationError as exc:  # the optimised stack is not a valid corrector
        raise OpticsError(f"optimize --goal corrector: the optimised corrector is invalid ({exc})") from None
    new = new.model_copy(update={"name": f"{design.name}_corrector_opt"})
    before = rms_spots(tracer, fields, lam, wts, verify_rays, seed=seed + 1)
    after = rms_spots(SequentialTracer(new, mi), fields, lam, wts, verify_rays, seed=seed + 1)
    variables = {n: (float(a), float(b)) for n, a, b in zip(names, x0, sol.x)}
    return CorrectorResult(new, fields, before * 1e3, after * 1e3, variables, int(sol.nfev),
                           time.perf_counter() - t0, history)


# ---- baffle --------------------------------------------------------------------------------------------
def corner_field_deg(design: Design) -> tuple[float, float]:
    """Field angles [deg] of a star imaged at the sensor's corner (-u, -v quadrant: the focuser side, where
    the tilted diagonal vignettes most), from the focal length: (atan(w/2f), atan(h/2f))."""
    f = design.primary.focal_length_mm
    fp = design.focal_plane
    return (math.degrees(math.atan(0.5 * fp.width_mm / f)), math.degrees(math.atan(0.5 * fp.height_mm / f)))


def corner_illumination(design: Design, mi, rays: int = 200_000, seed: int = 0) -> float:
    """Relative illumination at the sensor's corner: throughput there over the on-axis throughput (hard
    edges, every obstruction; the same pupil points for both)."""
    tr = SequentialTracer(design, mi)
    px, py = pupil_uniform(rays, tr.layout.r_primary, seed=seed)
    # the corner's image lies a little inside the sensor: 0.98 of the corner field
    cx, cy = corner_field_deg(design)
    return tr.count((0.98 * cx, 0.98 * cy), px, py) / max(tr.count((0.0, 0.0), px, py), 1)


def _baffle_design(design: Design, vanes: int, zone_start: float, inner_d: float) -> Design:
    data = design.model_dump()
    data["baffle"].update(vanes=int(vanes), zone_start_mm=float(zone_start), vane_inner_diameter_mm=float(inner_d))
    return Design.model_validate(data)


def _default_zone_start(design: Design) -> float:
    from .layout import make_layout

    L = make_layout(design)
    return float(L.vane_z[0]) if L.vane_z else float(min(L.spider_z[1] + 20.0, design.tube.length_mm - 1.0))


@dataclass
class BaffleResult:
    design: Design
    angles_deg: list
    pst_before: np.ndarray
    pst_before_err: np.ndarray
    pst_after: np.ndarray
    pst_after_err: np.ndarray
    corner_before: float
    corner_after: float
    start: dict
    best: dict
    evaluations: int
    seconds: float
    history: list = field(default_factory=list)

    def to_json(self) -> dict:
        return {"goal": "baffle", "angles_deg": list(self.angles_deg),
                "pst_before": self.pst_before.tolist(), "pst_before_rel_err": self.pst_before_err.tolist(),
                "pst_after": self.pst_after.tolist(), "pst_after_rel_err": self.pst_after_err.tolist(),
                "pst_ratio": (self.pst_after / self.pst_before).round(4).tolist(),
                "corner_relative_illumination_before": round(self.corner_before, 5),
                "corner_relative_illumination_after": round(self.corner_after, 5),
                "corner_change": round(self.corner_after / self.corner_before - 1.0, 5),
                "start": self.start, "best": self.best, "evaluations": self.evaluations,
                "seconds": round(self.seconds, 2), "history": self.history}


def optimize_baffle(design: Design, mi, angles_deg, *, rays: int = 100_000, verify_rays: int = 400_000,
                    max_evals: int = 30, max_corner_change: float = 0.01, vanes_range=(1, 12), seed: int = 0,
                    wavelength_nm: float = 550.0, progress=None) -> BaffleResult:
    """Derivative-free search for the vanes' number, lowest height and inner diameter (module docstring)."""
    from . import straylight

    t0 = time.perf_counter()
    angles = [float(a) for a in angles_deg]
    corner0 = corner_illumination(design, mi)
    start = {"vanes": design.baffle.vanes, "zone_start_mm": round(_default_zone_start(design), 3),
             "vane_inner_diameter_mm": design.baffle.vane_inner_diameter_mm}
    D, T = design.primary.diameter_mm, design.tube.inner_diameter_mm
    zmin = min(design.primary.focal_length_mm - design.secondary.distance_to_focus_mm + 0.5 *
               design.secondary.minor_axis_mm, design.tube.length_mm - 2.0)
    bounds = {"vanes": vanes_range, "zone_start_mm": (zmin, design.tube.length_mm - 1.0),
              "vane_inner_diameter_mm": (D + 1.0, T)}
    history = []
    evals = {"n": 0}

    def cost(p) -> tuple[float, float]:
        key = (int(p["vanes"]), round(p["zone_start_mm"], 3), round(p["vane_inner_diameter_mm"], 3))
        for h in history:
            if tuple(h["params"].values()) == key:
                return h["cost"], h["corner"]
        from pydantic import ValidationError

        try:
            d = _baffle_design(design, *key)
        except ValidationError:            # e.g. vanes closing the aperture: not a design
            return math.inf, math.nan
        corner = corner_illumination(d, mi)
        if abs(corner / corner0 - 1.0) > max_corner_change:
            c = math.inf
        else:
            r = straylight.pst_curve(d, mi, angles, rays=rays, seed=seed, wavelength_nm=wavelength_nm)
            c = float(np.mean(np.log10(np.maximum(r.pst, 1e-30))))
        evals["n"] += 1
        history.append({"params": dict(zip(("vanes", "zone_start_mm", "vane_inner_diameter_mm"), key)),
                        "cost": c, "corner": corner})
        if progress:
            progress(evals["n"], max_evals)
        return c, corner

    cur = dict(start)
    cur_cost, _ = cost(cur)
    steps = {"vanes": 2, "zone_start_mm": 0.25 * (bounds["zone_start_mm"][1] - bounds["zone_start_mm"][0]),
             "vane_inner_diameter_mm": 0.25 * (T - D)}
    while evals["n"] < max_evals and (steps["zone_start_mm"] > 2.0 or steps["vanes"] >= 1):
        improved = False
        for key in ("vanes", "vane_inner_diameter_mm", "zone_start_mm"):
            for sgn in (+1, -1):
                if evals["n"] >= max_evals:
                    break
                cand = dict(cur)
                lo, hi = bounds[key]
                cand[key] = min(max(cur[key] + sgn * steps[key], lo), hi)
                if key == "vanes":
                    cand[key] = round(cand[key])
                if cand[key] == cur[key]:
                    continue
                c, _ = cost(cand)
                if c < cur_cost:
                    cur, cur_cost, improved = cand, c, True
                    break
        if not improved:
            steps = {"vanes": steps["vanes"] // 2, "zone_start_mm": steps["zone_start_mm"] / 2,
                     "vane_inner_diameter_mm": steps["vane_inner_diameter_mm"] / 2}
            if steps["vanes"] == 0 and steps["zone_start_mm"] <= 2.0:
                break
    best = _baffle_design(design, int(cur["vanes"]), cur["zone_start_mm"], cur["vane_inner_diameter_mm"])
    best = best.model_copy(update={"name": f"{design.name}_baffle_opt"})
    # independent re-estimate of both (another seed, more rays)
    rb = straylight.pst_curve(design, mi, angles, rays=verify_rays, seed=seed + 1, wavelength_nm=wavelength_nm)
    ra = straylight.pst_curve(best, mi, angles, rays=verify_rays, seed=seed + 1, wavelength_nm=wavelength_nm)
    return BaffleResult(best, angles, rb.pst, rb.rel_err, ra.pst, ra.rel_err, corner0,
                        corner_illumination(best, mi), start,
                        {k: (round(v, 3) if isinstance(v, float) else v) for k, v in cur.items()}, evals["n"],
                        time.perf_counter() - t0, history)


# ---- output --------------------------------------------------------------------------------------------
def design_toml(design: Design, comment: str = "") -> str:
    """The design as TOML (``tomli_w``), with a leading comment."""
    import tomli_w

    data = design.model_dump(mode="json", exclude_none=True)
    data.pop("name", None)
    if design.perturbation.is_zero:
        data.pop("perturbation", None)
    head = "".join(f"# {line}\n" for line in comment.splitlines()) if comment else ""
    return head + tomli_w.dumps(data)


def plot_corrector(res: CorrectorResult, path, title: str = ""):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    idx = np.arange(len(res.fields_deg))
    ax[0].bar(idx - 0.2, res.rms_before_um * 2, 0.4, label="before")
    ax[0].bar(idx + 0.2, res.rms_after_um * 2, 0.4, label="after")
    ax[0].set_xticks(idx, [f"{x:+.2f},{y:+.2f}" for x, y in res.fields_deg], rotation=60, fontsize=7)
    ax[0].set_ylabel("RMS spot diameter [um]")
    ax[0].set_xlabel("field (theta_x, theta_y) [deg]")
    ax[0].legend()
    ax[1].plot(res.history, ".-")
    ax[1].set_xlabel("evaluation")
    ax[1].set_ylabel("mean RMS radius [um], optimiser")
    fig.suptitle(title or "corrector optimisation")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def plot_baffle(res: BaffleResult, path, title: str = ""):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    a = np.asarray(res.angles_deg)
    ax[0].errorbar(a, res.pst_before, yerr=res.pst_before * res.pst_before_err, fmt="o-", label="before")
    ax[0].errorbar(a, res.pst_after, yerr=res.pst_after * res.pst_after_err, fmt="s-", label="after")
    ax[0].set_yscale("log")
    ax[0].set_xlabel("off-axis angle [deg]")
    ax[0].set_ylabel("PST")
    ax[0].legend()
    costs = [h["cost"] for h in res.history]
    ax[1].plot([c if np.isfinite(c) else np.nan for c in costs], "o")
    ax[1].set_xlabel("evaluation")
    ax[1].set_ylabel("mean log10 PST (inf: vignettes the corner)")
    fig.suptitle(title or f"baffle optimisation: corner RI {res.corner_before:.4f} -> {res.corner_after:.4f}")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path

"""Cosmic rays: charged-particle tracks adding charge to the pixels they cross (stage CHARGE).

The physics (Bethe energy loss, shielding, cosine-law incidence, exact rasterisation, diffusion) lives in
:mod:`detector.cosmics`; this adapter draws the tracks of a frame once, over the whole read-out window,
from the frame seed (:meth:`CosmicRays.prepare_frame`), and each row-band tile adds the part of the charge
that falls on its rows. Tracks are therefore continuous across tile boundaries and the frame is the same
bytes whatever the number of threads.

References: PDG Review of Particle Physics (2022) ch. 34 "Passage of particles through matter" (eq. 34.5)
and ch. 30 "Cosmic rays"; thesis eqs. 11-13; the sources of the flux presets are in
:data:`detector.cosmics.ENVIRONMENTS`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from .. import cosmics
from ..errors import DetectorError
from ..rng import generator
from ..signatures import TRACK_K, GroupSignature, group_excess, is_track, on_source, outlier_pixels
from ..significance import FRAME_FALSE_ALARM
from .base import Effect, EffectParams, Stage, Tile, register_effect

#: Refuse frames expecting more hits than this (memory: ~ 200 bytes per hit); split the exposure instead.
MAX_EXPECTED_HITS = 5_000_000

_SHIELDS = {"none": None, "aluminium": "Al", "copper": "Cu"}


@dataclass(frozen=True)
class CosmicFrame:
    """Per-frame state shared read-only by all tiles.

    ``tracks`` is the table of :data:`detector.cosmics.TRACK_DTYPE` (sensor coordinates); ``rows``,
    ``cols``, ``charge_e`` are the rasterised pieces of all tracks (absolute sensor pixel, electrons),
    sorted by row so a tile finds its rows with ``searchsorted``.
    """

    tracks: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    charge_e: np.ndarray


#: one-sided confidence of the Poisson interval of the track count (Garwood 1936, Biometrika 28, 437): the data
#: cannot tell the rate from the environment's flux while that flux lies inside it; a test of the whole frame,
#: false this rarely per frame (FRAME_FALSE_ALARM)
TRACK_RATE_CONFIDENCE = 1.0 - FRAME_FALSE_ALARM


def window_area_cm2(sensor) -> float:
    """Area of the read-out window [cm^2]: its sensor pixels times the pixel pitch squared (the A of the hits
    F A t)."""
    w, h = sensor.roi_shape
    return w * h * (sensor.pixel_pitch_um * 1e-4) ** 2


def tracks(res, groups: np.ndarray) -> np.ndarray:
    """The groups of bright pixels that may be particle tracks (:func:`detector.signatures.is_track`: two or
    more pixels, the charge spread over them, narrower than a point-spread function, not touching a saturated
    or flagged pixel), not on the model's sources."""
    if groups.size == 0:
        return groups
    ok = is_track(groups)
    ok[ok] &= ~on_source(res, groups["peak"][ok])
    return groups[ok]


def poisson_interval(n: int, confidence: float = TRACK_RATE_CONFIDENCE) -> tuple[float, float]:
    """The one-sided lower and upper limits of a Poisson mean from ``n`` events at ``confidence`` each
    (Garwood 1936: chi2 quantiles of 2n and 2n + 2 degrees of freedom)."""
    from scipy.stats import chi2

    a = 1.0 - confidence
    lo = 0.5 * float(chi2.ppf(a, 2 * n)) if n > 0 else 0.0
    return lo, 0.5 * float(chi2.ppf(confidence, 2 * n + 2))


def _cosmic_groups(res):
    """Particle tracks from the chi2 their groups of bright pixels carry beyond the model's realisation
    (:func:`detector.signatures.group_gain`); the flux from their number over the window's area and the
    exposure (its maximum-likelihood estimate: what --apply renders gives this window the tracks it shows; a few
    tracks on a small window "measure" a rate a hundred times the ground muons', which the floor judges on the
    count's Poisson interval, not on this estimate)."""
    if res.exptime_s <= 0:
        return None
    npx = outlier_pixels(res)
    got = group_excess(tracks(res, res.data_spikes.pos_groups), tracks(res, res.model_spikes.pos_groups), TRACK_K,
                       npx)
    if got is None:
        return None
    delta, n_data, n_model = got
    exposure = window_area_cm2(res.sensor) * res.exptime_s  # [cm^2 s]
    # the rate's estimate; its floor (scenes' cosmic_rays_floor) judges the count's Poisson interval
    flux = (n_data - n_model) / exposure
    return {"flux_per_cm2_s": round(float(min(flux, 1e5)), 6)}, delta, n_data, n_model, 1


_COSMIC_SIGNATURE = GroupSignature(
    _cosmic_groups,
    lambda p, res: (f"thin groups of bright pixels at random places (tracks), {p['flux_per_cm2_s']:.3g} per cm2 "
                    "per s: cosmic rays (or radioactivity)"),
    pattern="positive multi-pixel tracks narrower than the PSF")


class CosmicRayParams(EffectParams):
    environment: Literal["ground", "leo", "saa", "geo"] = Field(
        "ground", description="preset particle flux, particle and spectrum (see detector.cosmics.ENVIRONMENTS)")
    flux_per_cm2_s: float | None = Field(
        None, ge=0, le=1e5, description="particles crossing the sensor plane; overrides the preset [cm^-2 s^-1]",
        json_schema_extra={"unit": "cm-2 s-1"})
    particle: Literal["auto", "proton", "muon", "alpha"] = Field(
        "auto", description="projectile; 'auto' = the preset's (muon on the ground, proton in orbit)")
    energy_mev: float | None = Field(
        None, gt=0, le=1e7, description="fixed kinetic energy; default: drawn from the power-law spectrum [MeV]",
        json_schema_extra={"unit": "MeV"})
    energy_min_mev: float | None = Field(
        None, gt=0, le=1e6, description="lower end of the E^-index spectrum; default: the preset's [MeV]",
        json_schema_extra={"unit": "MeV"})
    energy_max_mev: float = Field(1e5, gt=0, le=1e7, description="upper end of the spectrum [MeV]",
                                  json_schema_extra={"unit": "MeV"})
    spectrum_index: float = Field(2.7, ge=0, le=6, description="differential index gamma of dN/dE ~ E^-gamma [1]",
                                  json_schema_extra={"unit": "1"})
    depletion_um: float = Field(10.0, gt=0, le=1000, description="sensitive (depleted/epitaxial) Si thickness [um]",
                                json_schema_extra={"unit": "um"})
    theta_max_deg: float = Field(89.0, ge=0, lt=90, json_schema_extra={"unit": "deg"},
                                 description="largest zenith angle; steeper tracks are clamped to it [deg]")
    shielding_material: Literal["none", "aluminium", "copper"] = Field(
        "none", description="planar shield in front of the sensor")
    shielding_mm: float = Field(0.0, ge=0, le=1000, description="shield thickness (normal to the sensor) [mm]",
                                json_schema_extra={"unit": "mm"})
    diffusion_sigma_px: float = Field(0.5, ge=0, le=5, description="Gaussian charge-diffusion std [pixels]",
                                      json_schema_extra={"unit": "pixel"})
    pair_energy_ev: float = Field(cosmics.SI_PAIR_ENERGY_EV, ge=3.0, le=4.0,
                                  description="energy per electron-hole pair in Si [eV]",
                                  json_schema_extra={"unit": "eV"})

    @model_validator(mode="after")
    def _check(self):
        lo = self.energy_min_mev if self.energy_min_mev is not None else 0.0
        if self.energy_max_mev <= lo:
            raise ValueError(f"energy_max_mev ({self.energy_max_mev}) must exceed energy_min_mev ({lo})")
        if self.shielding_mm > 0 and self.shielding_material == "none":
            raise ValueError("shielding_mm > 0 needs shielding_material 'aluminium' or 'copper'")
        return self


@register_effect
class CosmicRays(Effect):
    """Cosmic-ray (and muon) tracks: straight segments of charge added to the drawn charge (stage CHARGE).

    Hits arrive as a Poisson process of mean ``F A t`` (F the flux through the sensor plane, A the area of
    the read-out window, t the exposure), with cosine-law zenith angles and uniform azimuths. Each particle
    is slowed by an optional aluminium/copper shield (CSDA with the Bethe stopping power, PDG eq. 34.5;
    stopped particles are removed) and loses the Bethe mean energy along its path ``d / cos(theta)``
    through the sensitive layer, ``N = E_dep / 3.6 eV`` electrons, spread uniformly along the projected
    segment of length ``d tan(theta)``, rasterised exactly and blurred by a Gaussian of
    ``diffusion_sigma_px``. Mean loss only: no Landau fluctuations (see :mod:`detector.cosmics`).
    Charge is added before the full-well clip. FITS table ``COSMICS``: x, y, x_end, y_end (output-frame
    pixels), theta_deg, phi_deg, energy_mev (at the sensor), energy_incident_mev (before the shield),
    deposit_mev, electrons.
    """

    name = "cosmic_rays"
    scaling = "frame"
    identity = {"flux_per_cm2_s": 0.0}
    stages = (Stage.CHARGE,)
    stochastic = True  # compared by its statistics (tail counts), not pixel by pixel
    signature = _COSMIC_SIGNATURE
    Params = CosmicRayParams

    def setup(self) -> None:
        p = self.params
        env = cosmics.ENVIRONMENTS[p.environment]
        self.flux_per_cm2_s = env.flux_per_cm2_s if p.flux_per_cm2_s is None else p.flux_per_cm2_s
        self.particle = cosmics.PARTICLES[env.particle if p.particle == "auto" else p.particle]
        self.energy_min_mev = env.energy_min_mev if p.energy_min_mev is None else p.energy_min_mev
        if p.energy_mev is None and self.energy_min_mev >= p.energy_max_mev:
            raise DetectorError(f"energy_max_mev {p.energy_max_mev} is below the spectrum's lower end "
                                f"{self.energy_min_mev} MeV", key=f"effects.{self.name}.energy_max_mev",
                                expected=f"> {self.energy_min_mev}")
        self.kernel = cosmics.diffusion_kernel(p.diffusion_sigma_px)

    def expected_hits(self, exptime_s: float) -> float:
        """Mean number of particles hitting the read-out window during ``exptime_s``: F A t [1]."""
        area_cm2 = window_area_cm2(self.sensor)
        return self.flux_per_cm2_s * area_cm2 * max(float(exptime_s), 0.0)

    def prepare_frame(self, exptime_s: float, frame_seed: int) -> CosmicFrame:
        p, s = self.params, self.sensor
        mu = self.expected_hits(exptime_s)
        if mu > MAX_EXPECTED_HITS:
            raise DetectorError(f"{mu:.3g} cosmic-ray hits expected in one frame", key=f"effects.{self.name}",
                                expected=f"at most {MAX_EXPECTED_HITS:.0e}: lower the flux or split the exposure")
        w, h = s.roi_shape
        tracks = cosmics.draw_tracks(
            generator(frame_seed, self.name), mu,
            (s.roi_x0 - 0.5, s.roi_x0 + w - 0.5), (s.roi_y0 - 0.5, s.roi_y0 + h - 0.5),
            s.pixel_pitch_um, p.depletion_um, self.particle, p.energy_mev, self.energy_min_mev,
            p.energy_max_mev, p.spectrum_index, _SHIELDS[p.shielding_material], p.shielding_mm,
            p.theta_max_deg, p.pair_energy_ev)
        _, rows, cols, q = cosmics.rasterise_segments(tracks["x_sensor"], tracks["y_sensor"],
                                                      tracks["x_end_sensor"], tracks["y_end_sensor"],
                                                      tracks["electrons"])
        order = np.argsort(rows, kind="stable")
        return CosmicFrame(tracks, rows[order], cols[order], q[order])

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        st: CosmicFrame | None = tile.state.get(self.name)
        if st is None or st.rows.size == 0:
            return
        r = (self.kernel.size - 1) // 2
        lo = np.searchsorted(st.rows, tile.y0 - r, side="left")
        hi = np.searchsorted(st.rows, tile.y1 + r, side="left")
        if hi <= lo:
            return
        # tile.bin is 1 at the CHARGE stage (binning comes after the full-well clip)
        cosmics.add_charge(data, st.rows[lo:hi] - tile.y0, st.cols[lo:hi] - tile.x0, st.charge_e[lo:hi],
                           self.kernel)

    def truth(self, state: CosmicFrame | None = None) -> dict[str, np.ndarray]:
        t = state.tracks if state is not None else np.zeros(0, dtype=cosmics.TRACK_DTYPE)
        s = self.sensor
        b = s.binning
        cx = s.roi_x0 + (b - 1) / 2.0  # sensor coordinate of the centre of output pixel 0
        cy = s.roi_y0 + (b - 1) / 2.0
        out = np.zeros(t.size, dtype=[("x", "f8"), ("y", "f8"), ("x_end", "f8"), ("y_end", "f8"),
                                      ("theta_deg", "f4"), ("phi_deg", "f4"), ("energy_mev", "f8"),
                                      ("energy_incident_mev", "f8"), ("deposit_mev", "f8"), ("electrons", "f4")])
        out["x"], out["y"] = (t["x_sensor"] - cx) / b, (t["y_sensor"] - cy) / b
        out["x_end"], out["y_end"] = (t["x_end_sensor"] - cx) / b, (t["y_end_sensor"] - cy) / b
        for k in ("theta_deg", "phi_deg", "energy_mev", "energy_incident_mev", "deposit_mev", "electrons"):
            out[k] = t[k]
        return {"COSMICS": out}

"""The optics' PSF over the field, integrated over the detector pixels (``[psf] model = "optics"``).

The optics computes PSF stamps at a few field points (:func:`optics.psf.psf_grid`, a FITS cube read by
:func:`optics.psf.read_psf_fits`): ``images[k]`` holds the fraction of the energy of a star at field angles
``fields_deg[k]`` in each cell of ``pixel_um`` (the cells of the optics, not the detector's), rows along
the focal-plane v axis. This module turns them into the pixel-integrated PSF of the detector
(:mod:`scenes.image.psf` hook: ``psf(x, y, dx, dy)`` and ``radius_px``).

Pixel integration. A cell holds the exact integral of the intensity over its area, so the cumulative
energy ``F(x, y) = integral_{-inf}^{x} integral_{-inf}^{y} I`` is known exactly at the cell corners. The
energy a detector pixel [x1, x2] x [y1, y2] receives is

    P = F(x2, y2) - F(x1, y2) - F(x2, y1) + F(x1, y1),                                            (1)

with F between the corners from a tensor-product cubic convolution (Keys 1981, IEEE ASSP 29, 1153;
a = -1/2, third-order accurate, interpolating: on the corners it is exact, so a pixel aligned with the
cells gets exactly their sum). Outside the stamp F is constant (0 before, the total after), so the pixels
of a stamp that covers the cube's stamp hold **exactly its energy**, whatever the sub-pixel position and
the ratio of the cell to the pixel. (Linear interpolation of F would be the overlap of the cells with the
pixels: exact for a piecewise-constant intensity, but it widens the PSF by a cell-wide box, variance
cell^2/12; the cubic does not.) Values below zero (the cubic's overshoot where F has steps: ~1e-8 of the flux
for a smooth PSF, ~1e-3 for the ray histogram of a geometric grid) are set to zero and the stamp is scaled
back to the energy it held, so the flux stays exact.

Centring. Every grid PSF is shifted (by resampling its F) so that its centroid lies at the origin: a star
is drawn with its centroid on the position the frame's WCS gives (the chief-ray SIP of the optics; the
cube's stamps are centred on the unobstructed bundle's mean, which the WCS does not know), so the centroid
is unbiased and the WCS is what an astrometric pipeline recovers.

Field interpolation. Between the grid points the PSF is the **bilinear** blend of the four surrounding
grid PSFs (in the ideal, undistorted pixel position of the star: the field angle), held constant beyond
the outermost points. Bilinear rather than nearest: the PSF then varies continuously over the field (a
streak does not jump in shape where it crosses a cell boundary), the blend of normalised, centred PSFs is
normalised and centred, and it costs four array additions. Its limit: a blend of two differently shaped
PSFs is not the PSF in between (a 3 x 3 grid across a field where coma grows quickly leaves a blend of
shapes). A grid that is not a rectangular lattice falls back to the nearest grid point.

Seeing and jitter. A Gaussian of rms sigma^2 = (seeing FWHM / 2.3548)^2 + jitter^2 per axis is
convolved with each grid PSF: the cell integrals are samples of the cell-box-smoothed intensity, so a
discrete convolution with point samples of the Gaussian (:func:`gaussian_cell_kernel`) gives the cell
integrals of the convolved intensity and adds exactly sigma^2 to the variance (a kernel of Gaussian *cell
integrals* would add another cell box, s^2/12); the stamps are padded to hold its wings.

Orientation. The optics' focal plane (u, v) is read as pixels x = u / pitch, y = -v / pitch (see
:mod:`scenes.projection`): the stamps' rows are flipped. A grid point's ideal position is
(x, y) = axis + (-f tan theta_x, +f tan theta_y) / pitch, f the primary's focal length (the convention of
:func:`optics.distortion.fit_sip`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import convolve1d

from optics.psf import cached_psf_grid, read_psf_fits

from ..errors import SceneError
from .psf import GAUSS_FWHM

CHUNK_SAMPLES = 64  # samples blended at once (memory: 8 (M + 1)^2 bytes each)


def keys_weights(t) -> tuple[np.ndarray, np.ndarray]:
    """Node indices (..., 4) and weights (..., 4) of the Keys (a = -1/2) cubic at positions ``t`` [nodes]."""
    t = np.asarray(t, dtype=float)
    i = np.floor(t)
    f = t - i
    f2, f3 = f * f, f * f * f
    w = np.stack([-0.5 * f3 + f2 - 0.5 * f, 1.5 * f3 - 2.5 * f2 + 1.0, -1.5 * f3 + 2.0 * f2 + 0.5 * f,
                  0.5 * f3 - 0.5 * f2], axis=-1)
    idx = i.astype(np.int64)[..., None] + np.arange(-1, 3)
    return idx, w


def cumulative(images: np.ndarray) -> np.ndarray:
    """Cumulative energy at the cell corners: (K, N, N) cells -> (K, N + 1, N + 1), F[:, 0, :] = F[:, :, 0] = 0."""
    k, ny, nx = images.shape
    f = np.zeros((k, ny + 1, nx + 1))
    f[:, 1:, 1:] = np.cumsum(np.cumsum(images, axis=1), axis=2)
    return f


def interp_cdf(f: np.ndarray, ty: np.ndarray, tx: np.ndarray) -> np.ndarray:
    """F (m, M + 1, M + 1) at node positions ``ty`` (m, a) x ``tx`` (m, b) -> (m, a, b); F held beyond its ends."""
    m, ny, nx = f.shape
    ix, wx = keys_weights(tx)  # (m, b, 4)
    iy, wy = keys_weights(ty)
    ix = np.clip(ix, 0, nx - 1)
    iy = np.clip(iy, 0, ny - 1)
    r = np.arange(m)[:, None, None]
    g = np.zeros((m, ny, tx.shape[1]))
    for j in range(4):
        g += f[r, np.arange(ny)[None, :, None], ix[:, None, :, j]] * wx[:, None, :, j]
    out = np.zeros((m, ty.shape[1], tx.shape[1]))
    for j in range(4):
        out += g[r, iy[:, :, j][:, :, None], np.arange(tx.shape[1])[None, None, :]] * wy[:, :, j][:, :, None]
    return out


def gaussian_cell_kernel(sigma_cells: float) -> np.ndarray:
    """Discrete kernel (odd length, sum 1) that convolves cell integrals with a Gaussian of rms ``sigma_cells``.

    The cells hold samples of the box-integrated intensity B * I; convolving those samples with point samples
    of the Gaussian G gives samples of B * I * G (exact for band-limited B * I): from 1 cell on, the sampled
    Gaussian's variance is sigma^2 to 2e-7. Narrower Gaussians are not resolved by the cells; they get the
    taps [b, a, 1 - 2a - 2b, a, b] with the Gaussian's second and fourth moments (2a + 8b = sigma^2,
    2a + 32b = 3 sigma^4; b = 0 below sigma = 1/sqrt3, keeping the variance exact).
    """
    s = float(sigma_cells)
    if s <= 0:
        return np.ones(1)
    if s < 1.0:
        b = max(3.0 * s ** 4 - s * s, 0.0) / 24.0
        a = (s * s - 8.0 * b) / 2.0
        return np.array([b, a, 1.0 - 2.0 * a - 2.0 * b, a, b])
    n = math.ceil(8.0 * s) + 1
    d = np.arange(-n, n + 1, dtype=float)
    k = np.exp(-0.5 * (d / s) ** 2)
    return k / k.sum()


def _convolve(images: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    if kernel.size == 1:
        return images
    out = convolve1d(images, kernel, axis=1, mode="constant")
    return convolve1d(out, kernel, axis=2, mode="constant")


def _centroids(images: np.ndarray) -> np.ndarray:
    """(K, 2) centroids (x, y) [cells] about the stamp centre."""
    ny, nx = images.shape[1:]
    xs = np.arange(nx) - (nx - 1) / 2.0
    ys = np.arange(ny) - (ny - 1) / 2.0
    tot = images.sum(axis=(1, 2))
    return np.stack([(images.sum(axis=1) * xs).sum(axis=1) / tot, (images.sum(axis=2) * ys).sum(axis=1) / tot], -1)


def recentre(images: np.ndarray, iterations: int = 3) -> np.ndarray:
    """Shift each stamp (by resampling its cumulative energy) so that its centroid is the stamp centre."""
    out = images
    for _ in range(iterations):
        c = _centroids(out)
        if np.max(np.abs(c)) < 1e-9:
            break
        ny, nx = out.shape[1:]
        pad = math.ceil(np.max(np.abs(c))) + 2
        f = cumulative(np.pad(out, ((0, 0), (pad, pad), (pad, pad))))
        tx = np.arange(nx + 2 * pad + 1, dtype=float)[None, :] + c[:, 0:1]  # F'(E) = F(E + c): centroid -> centre
        ty = np.arange(ny + 2 * pad + 1, dtype=float)[None, :] + c[:, 1:2]
        g = interp_cdf(f, ty, tx)
        out = np.diff(np.diff(g, axis=1), axis=2)
        out = np.maximum(out, 0.0)
        out /= out.sum(axis=(1, 2), keepdims=True)
    return out


@dataclass
class GridPSF:
    """Field-dependent, pixel-integrated PSF from an optics PSF grid (module notes).

    Build it with :meth:`from_grid`. Coordinates are unbinned pixels of the read-out window (0-based).

    Attributes
    ----------
    cdf : (K, M + 1, M + 1) cumulative energy of the centred grid PSFs at the cell corners (scene axes)
    step_px : cell size [unbinned pixels]
    node_x, node_y : ideal positions of the grid lattice [window pixels] (sorted), ``plane[j, i]`` the
        grid PSF at (node_x[i], node_y[j]); ``plane`` None with ``points`` (K, 2): nearest-point mode
    to_ideal : callable (x, y) -> ideal (x, y), the frame's forward distortion (None: none)
    fwhm_px : nominal FWHM (mean of the grid's, with the seeing/jitter Gaussian) [pixels]
    """

    cdf: np.ndarray
    step_px: float
    node_x: np.ndarray
    node_y: np.ndarray
    plane: np.ndarray | None
    points: np.ndarray
    fwhm_px: float
    jitter_px: float = 0.0
    seeing_fwhm_px: float = 0.0
    to_ideal: object = None
    meta: dict = field(default_factory=dict)

    @classmethod
    def from_grid(cls, grid, pitch_um: float, focal_length_mm: float, axis_xy: tuple[float, float], *,
                  jitter_px: float = 0.0, seeing_fwhm_px: float = 0.0, to_ideal=None) -> GridPSF:
        """From an :class:`optics.psf.PSFGrid`.

        Parameters
        ----------
        grid : PSFGrid (``images``, ``pixel_um``, ``fields_deg``, ``metrics``)
        pitch_um : detector pixel pitch [um] (unbinned)
        focal_length_mm : focal length that maps field angles to ideal positions, f tan(theta) [mm]
        axis_xy : optical axis in the window's unbinned pixels (0-based)
        jitter_px, seeing_fwhm_px : Gaussian jitter rms per axis and seeing FWHM [pixels]
        to_ideal : the frame's forward distortion, window pixels -> ideal window pixels
        """
        images = np.clip(np.asarray(grid.images, dtype=float), 0.0, None)
        if images.ndim != 3 or images.shape[1] < 3 or images.shape[2] < 3:
            raise ValueError(f"PSF grid images of shape {images.shape}: expected (K, N, N) stamps")
        images = images[:, ::-1, :]  # rows along v -> rows along y = -v / pitch
        images = images / images.sum(axis=(1, 2), keepdims=True)
        step = float(grid.pixel_um) / float(pitch_um)
        sigma = math.hypot(seeing_fwhm_px / GAUSS_FWHM, jitter_px)
        if sigma > 0:
            kern = gaussian_cell_kernel(sigma / step)
            h = kern.size // 2
            images = _convolve(np.pad(images, ((0, 0), (h, h), (h, h))), kern)
            images /= images.sum(axis=(1, 2), keepdims=True)
        images = np.pad(recentre(images), ((0, 0), (2, 2), (2, 2)))  # F constant over the last two corners
        fields = np.asarray(grid.fields_deg, dtype=float).reshape(-1, 2)
        f_px = focal_length_mm * 1e3 / pitch_um
        px = axis_xy[0] - f_px * np.tan(np.radians(fields[:, 0]))
        py = axis_xy[1] + f_px * np.tan(np.radians(fields[:, 1]))
        ux, uy = np.unique(np.round(px, 6)), np.unique(np.round(py, 6))
        plane = None
        if len(ux) * len(uy) == len(fields):
            plane = np.full((len(uy), len(ux)), -1, dtype=np.int64)
            for k in range(len(fields)):
                plane[np.searchsorted(uy, round(py[k], 6)), np.searchsorted(ux, round(px[k], 6))] = k
            if np.any(plane < 0):
                plane = None
        fw = [m.get("fwhm_um", math.nan) for m in (grid.metrics or [])]
        fwhm_opt = float(np.nanmean(fw)) / pitch_um if fw and np.any(np.isfinite(fw)) else math.nan
        if not np.isfinite(fwhm_opt):  # from the second moments of the stamps
            n = images.shape[-1]
            xs = (np.arange(n) - (n - 1) / 2.0) * step
            fwhm_opt = float(np.mean(GAUSS_FWHM * np.sqrt((images.sum(axis=1) * xs ** 2).sum(axis=1))))
        fwhm = math.hypot(fwhm_opt, GAUSS_FWHM * sigma)
        meta = {"kind": getattr(grid, "kind", ""), "design": getattr(grid, "design", ""), "n_fields": len(fields),
                "pixel_um": float(grid.pixel_um), "grid_seeing_arcsec": float(getattr(grid, "seeing_fwhm_arcsec", 0.0)),
                "grid_jitter_arcsec": float(getattr(grid, "jitter_rms_arcsec", 0.0))}
        return cls(cumulative(images), step, ux, uy, plane, np.stack([px, py], -1), fwhm, jitter_px, seeing_fwhm_px,
                   to_ideal, meta)

    # -- geometry
    @property
    def half_extent_px(self) -> float:
        """Half the side of the (padded, centred) stamps [pixels]."""
        return 0.5 * (self.cdf.shape[-1] - 1) * self.step_px

    def radius_px(self, flux_e) -> np.ndarray:
        """Stamp half-width covering the whole grid stamp from any sub-pixel position (all its energy)."""
        w = math.ceil(self.half_extent_px) + 1
        return np.full(np.shape(flux_e), w, dtype=np.int64)

    def field_weights(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Grid planes (n, 4) and bilinear weights (n, 4) at window positions ``x, y`` (module notes)."""
        x = np.atleast_1d(np.asarray(x, dtype=float))
        y = np.atleast_1d(np.asarray(y, dtype=float))
        if self.to_ideal is not None:
            x, y = self.to_ideal(x, y)
        if self.plane is None:  # nearest grid point
            d = (x[:, None] - self.points[None, :, 0]) ** 2 + (y[:, None] - self.points[None, :, 1]) ** 2
            k = np.argmin(d, axis=1)
            return np.repeat(k[:, None], 4, axis=1), np.tile([1.0, 0.0, 0.0, 0.0], (x.size, 1))

        def axis(nodes, q):
            if len(nodes) == 1:
                return np.zeros(q.shape, dtype=np.int64), np.zeros(q.shape, dtype=np.int64), np.zeros(q.shape)
            i = np.clip(np.searchsorted(nodes, q, side="right") - 1, 0, len(nodes) - 2)
            f = np.clip((q - nodes[i]) / (nodes[i + 1] - nodes[i]), 0.0, 1.0)
            return i, i + 1, f

        i0, i1, fx = axis(self.node_x, x)
        j0, j1, fy = axis(self.node_y, y)
        p = self.plane
        planes = np.stack([p[j0, i0], p[j0, i1], p[j1, i0], p[j1, i1]], -1)
        w = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], -1)
        return planes, w

    # -- the hook
    def __call__(self, x, y, dx, dy) -> np.ndarray:
        x = np.atleast_1d(np.asarray(x, dtype=float))
        y = np.atleast_1d(np.asarray(y, dtype=float))
        dx = np.asarray(dx, dtype=float)
        dy = np.asarray(dy, dtype=float)
        planes, w = self.field_weights(x, y)
        out = np.empty((x.size, dy.shape[1], dx.shape[1]))
        origin = -self.half_extent_px  # position of the first corner relative to the centroid [px]
        for a in range(0, x.size, CHUNK_SAMPLES):
            b = min(a + CHUNK_SAMPLES, x.size)
            f = np.einsum("mk,mkij->mij", w[a:b], self.cdf[planes[a:b]])
            out[a:b] = self._integrate(f, dx[a:b], dy[a:b], origin)
        return out

    def _integrate(self, f, dx, dy, origin) -> np.ndarray:
        """Eq. (1) for pixels at offsets ``dx`` (m, wx), ``dy`` (m, wy) from the centroids."""
        s = self.step_px
        cx = dx.shape[1] > 1 and np.all(np.diff(dx, axis=1) == 1.0)
        cy = dy.shape[1] > 1 and np.all(np.diff(dy, axis=1) == 1.0)
        if cx and cy:  # consecutive pixels share their edges: F at (wy + 1) x (wx + 1) corners
            ex = np.concatenate([dx - 0.5, dx[:, -1:] + 0.5], axis=1)
            ey = np.concatenate([dy - 0.5, dy[:, -1:] + 0.5], axis=1)
            g = interp_cdf(f, (ey - origin) / s, (ex - origin) / s)
            p = g[:, 1:, 1:] - g[:, :-1, 1:] - g[:, 1:, :-1] + g[:, :-1, :-1]
        else:
            wx, wy = dx.shape[1], dy.shape[1]
            ex = np.concatenate([dx - 0.5, dx + 0.5], axis=1)
            ey = np.concatenate([dy - 0.5, dy + 0.5], axis=1)
            g = interp_cdf(f, (ey - origin) / s, (ex - origin) / s)
            p = g[:, wy:, wx:] - g[:, :wy, wx:] - g[:, wy:, :wx] + g[:, :wy, :wx]
        total = p.sum(axis=(1, 2), keepdims=True)
        p = np.maximum(p, 0.0)
        kept = p.sum(axis=(1, 2), keepdims=True)
        return p * np.where(kept > 0, total / np.where(kept > 0, kept, 1.0), 0.0)

    def describe(self) -> dict:
        return {"model": "optics", "fwhm_px": self.fwhm_px, "jitter_px": self.jitter_px,
                "seeing_fwhm_px": self.seeing_fwhm_px, "interpolation": "bilinear" if self.plane is not None
                else "nearest", "grid": f"{len(self.node_x)}x{len(self.node_y)}" if self.plane is not None
                else str(len(self.points)), "step_px": self.step_px, **self.meta}


def optics_psf(scene, sensor, design, pixel_scale_arcsec: float, distortion=None) -> GridPSF:
    """The scene's ``[psf] model = "optics"``: the design's PSF grid (or ``grid_file``) as a :class:`GridPSF`.

    ``distortion``: the frame's :class:`scenes.projection.Sip` (unbinned sensor pixels about the optical
    axis), used to put each star at its ideal (field-angle) position for the field interpolation.
    """

    cfg = scene.psf
    pitch = sensor.pixel_pitch_um
    try:
        if cfg.grid_file is not None:
            path = cfg.grid_file
        else:
            path = cached_psf_grid(design, float(pitch), int(cfg.grid[0]), int(cfg.grid[1]))
        grid = read_psf_fits(path)
    except SceneError:
        raise
    except (OSError, KeyError, ValueError, ImportError) as exc:
        key = "psf.grid_file" if cfg.grid_file is not None else "psf.model"
        raise SceneError(f"cannot get the optics PSF grid: {exc}", key=key, file=scene.source,
                         expected="a PSF cube written by optics.psf.write_psf_fits") from None
    ax = (sensor.sensor_width_px - 1) / 2.0 - sensor.roi_x0
    ay = (sensor.sensor_height_px - 1) / 2.0 - sensor.roi_y0
    to_ideal = None
    if distortion is not None:
        def to_ideal(x, y, sip=distortion):
            u, v = sip.forward(np.asarray(x) - ax, np.asarray(y) - ay)
            return u + ax, v + ay
    return GridPSF.from_grid(grid, pitch, design.primary.focal_length_mm, (ax, ay),
                             jitter_px=cfg.jitter_rms_arcsec / pixel_scale_arcsec,
                             seeing_fwhm_px=cfg.seeing_fwhm_arcsec / pixel_scale_arcsec, to_ideal=to_ideal)

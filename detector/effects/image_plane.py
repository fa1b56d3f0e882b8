"""Image-plane effects of the optics: extra blur, pointing jitter and drift, a pointing offset, field distortion,
ghosts.

They act once per frame on the whole expected photo-electron image (stage FIELD), before the sensor, so a
scene can add them to any rendering (catalogue stars, streaks, a flat screen) and ``newtsim diagnose`` can
fit them to a measured frame without re-rendering the sources. The scene's ``[psf]`` and the optics
package remain the primary description of the PSF and distortion; these effects are the *corrections* a
comparison with real data asks for.

Every effect is a small transformation ``T`` of the image ``I``. For diagnosis each is linearised about
the identity (first-order Taylor expansion), which makes its signature a set of linear templates built
from the model image's derivatives:

* Gaussian blur of covariance ``C``: ``I * G_C ~ I + 1/2 (C_xx d2I/dx2 + 2 C_xy d2I/dxdy + C_yy d2I/dy2)``
  (heat equation: convolution with a Gaussian of variance s^2 is diffusion for a time s^2 / 2);
* shift by ``(dx, dy)``: ``I(x - dx, y - dy) ~ I - dx dI/dx - dy dI/dy``;
* uniform drift ``d`` during the exposure: convolution with a line segment (a box of length ``|d|``), whose
  covariance is ``d d^T / 12``, so to first order a blur of that (rank-one) covariance (the straight drift's
  start; an accelerating or bowed path, :func:`drift_path_px`, is then fitted from the straight one);
* radial distortion ``r' = r (1 + k r^2)``: a shift field ``k r^2 (x - x_c, y - y_c)``, plus Brown's (1966)
  decentering terms in ``p1``, ``p2``;
* ghost: ``alpha`` times the image reflected through the optical axis and defocused into a disc (a
  double reflection between two surfaces of a refractive corrector; Gross, *Handbook of Optical Systems*
  vol. 5, 2012, ch. 40 "ghost images"), which is linear in ``alpha``. The ``ghost`` effect itself (its other
  maps and profiles, and the search of its geometry) is in :mod:`detector.effects.ghosts`.

Coordinates are sensor pixels; the optical axis is at the sensor centre.
"""

from __future__ import annotations

import inspect
import os
from dataclasses import replace

import numpy as np
import scipy.fft
from pydantic import Field
from scipy import ndimage, signal, special

from ..signatures import (
    Fit,
    Signature,
    Variant,
    fit_linear,
    frame_at,
    profiled_chi2,
    search_sample,
)
from ..significance import (
    EXPLAINS_MOST,
    SCALE_TOLERANCE,
    STRUCTURE_SIGMA,
    TRAIL_MIN_FWHM,
    nested_gain_significant,
)
from .base import Effect, EffectParams, Stage, Tile, register_effect

# --- pure functions -------------------------------------------------------------------------------------------


def blur(image: np.ndarray, sigma_major_px: float, sigma_minor_px: float | None = None, angle_deg: float = 0.0,
         spectra: dict | None = None, workers: int | None = None, min_pad: int = 0) -> np.ndarray:
    """The image convolved with a (possibly elongated) Gaussian of principal widths [px] and major-axis angle
    (counter-clockwise from +x), flux conserving; edges are extended with their own values.

    Done in Fourier space, ``H(f) = exp(-2 pi^2 f^T C f)`` with ``C`` the covariance: exact for any width,
    including the sub-pixel ones a pixel-sampled kernel gets wrong (the output's second moments are the
    input's plus ``C``). ``spectra``, ``workers``: see :func:`fourier_filter`.
    """
    minor = sigma_major_px if sigma_minor_px is None else sigma_minor_px
    if sigma_major_px <= 0 and minor <= 0:
        return image.copy()
    c, s = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))
    rot = np.array([[c, -s], [s, c]])
    cov = rot @ np.diag([sigma_major_px ** 2, minor ** 2]) @ rot.T  # (x, y)
    return gaussian_filter_cov(image, cov, spectra=spectra, workers=workers, min_pad=min_pad)


#: padded spectra a ``spectra`` cache of :func:`fourier_filter` keeps at most (each ~ 16 bytes per pixel)
MAX_CACHED_SPECTRA = 3
#: filtered images a ``spectra`` cache of :func:`fourier_filter` keeps at most (each 8 bytes per pixel): a fit's
#: steps filter the same image with the same transfer function again (a Jacobian column whose parameter does not
#: enter that filter: a halo's share), which then costs nothing, not an inverse transform
MAX_CACHED_OUTPUTS = 2
#: threads of the diagnosis's Fourier transforms (:class:`TransformSignature`'s fits, the ghost scan and
#: :func:`detector.morphology.gaussian_nearest_fft`; the rendering's stay numpy's): the one setting for all
FIT_FFT_WORKERS = max(1, min(4, os.cpu_count() or 1))


def fourier_filter(image: np.ndarray, pad: int, transfer, spectra: dict | None = None, workers: int | None = None,
                   key: tuple | None = None) -> np.ndarray:
    """``image`` filtered in Fourier space by ``transfer(fx, fy)`` [cycles/px], edges extended by ``pad``
    pixels of their own values (so a frame's border does not wrap onto the opposite one).

    ``spectra``, optional: a dict the caller keeps for *one* ``image`` (a fit that filters the same image
    with many transfer functions): the padded image's spectrum is stored there by ``pad`` and reused
    (the same numbers as recomputing it). ``workers``: None, numpy's transforms (the rendering); a number,
    scipy's on that many threads (the diagnosis fits; the same transform to rounding, ~1e-15 relative).
    ``key``, optional with ``spectra``: a hashable that names ``transfer`` (its kind and parameters); the
    filtered image is then kept in ``spectra`` too and a second call with the same key returns it again (the
    same numbers: the same computation; the caller must not modify it)."""
    if workers is None:
        rfft2, irfft2 = np.fft.rfft2, np.fft.irfft2
    else:
        def rfft2(a):
            return scipy.fft.rfft2(a, workers=workers)

        def irfft2(a, s):
            return inverse_rfft2(a, s, workers)
    work = np.float64 if image.dtype == np.float64 else np.float32  # the diagnosis fits in double precision
    skey = (int(pad), np.dtype(work).str, image.shape, workers)
    okey = None if spectra is None or key is None else ("out", key, skey)
    if okey is not None and okey in spectra:
        return spectra[okey]
    cached = None if spectra is None else spectra.get(skey)
    if cached is None:
        # the padded sides grown on their far end to a length whose only prime factors are 2, 3 and 5: a
        # length with a large prime factor takes the transforms ~3x longer (2048 + 2 x 7 = 2 x 1031)
        grow = [scipy.fft.next_fast_len(n + 2 * pad, real=True) - n - 2 * pad for n in image.shape]
        big = np.pad(image.astype(work, copy=False), ((pad, pad + grow[0]), (pad, pad + grow[1])), mode="edge")
        cached = (rfft2(big), big.shape)
        del big
        if spectra is not None:
            _evict(spectra, False, MAX_CACHED_SPECTRA)
            spectra[skey] = cached
    spec, shape = cached
    fy = np.fft.fftfreq(shape[0])[:, None]
    fx = np.fft.rfftfreq(shape[1])[None, :]
    h = transfer(fx, fy)
    # a real transfer (a symmetric kernel) in the working precision; a complex one (an asymmetric kernel: a
    # curved or accelerating drift path) in the complex type of that precision
    h = h.astype(np.result_type(work, np.complex64) if np.iscomplexobj(h) else work, copy=False)
    out = irfft2(spec * h, s=shape)
    out = out[pad:pad + image.shape[0], pad:pad + image.shape[1]].astype(image.dtype)
    if okey is not None:
        _evict(spectra, True, MAX_CACHED_OUTPUTS)
        spectra[okey] = out
    return out


def inverse_rfft2(spec: np.ndarray, shape: tuple, workers: int | None) -> np.ndarray:
    """``scipy.fft.irfft2(spec, s=shape)`` as its two one-dimensional passes, the complex one in place: ``spec``
    (a temporary of the caller's) is overwritten. The same transform to rounding (~1e-15 relative); ~1.5x
    faster on a 2160^2 grid, where the two-dimensional call copies the half-spectrum once more."""
    half = scipy.fft.ifft(spec, axis=0, workers=workers, overwrite_x=True)
    return scipy.fft.irfft(half, n=shape[1], axis=1, workers=workers, overwrite_x=True)


def _evict(spectra: dict, outputs: bool, keep: int) -> None:
    """Drop the oldest entries of one kind (filtered images or spectra) from a ``spectra`` cache until fewer
    than ``keep`` are left."""
    mine = [k for k in spectra if (k[0] == "out") == outputs]
    for k in mine[:max(len(mine) - keep + 1, 0)]:
        spectra.pop(k)


def gaussian_filter_cov(image: np.ndarray, cov: np.ndarray, max_gain: float = 1.0, spectra: dict | None = None,
                        workers: int | None = None, min_pad: int = 0) -> np.ndarray:
    """``image`` convolved with a Gaussian of covariance ``cov`` [px^2, (x, y)]: ``H(f) = exp(-2 pi^2 f^T C f)``.

    ``C`` may have a negative eigenvalue (``max_gain > 1``): the image then becomes *narrower* along that
    axis (a deconvolution; the second moments still add: ``C_out = C_in + C``), the gain capped at
    ``max_gain`` at the high frequencies a smooth image does not hold anyway."""
    ev = np.linalg.eigvalsh(cov)
    pad = max(int(np.ceil(4 * np.sqrt(max(np.max(np.abs(ev)), 0.0)))) + 1, int(min_pad))

    def transfer(fx, fy):
        q = cov[0, 0] * fx * fx + 2 * cov[0, 1] * fx * fy + cov[1, 1] * fy * fy
        return np.minimum(np.exp(-2 * np.pi ** 2 * q), max_gain)

    key = ("gaussian", np.asarray(cov, np.float64).tobytes(), float(max_gain))
    return fourier_filter(image, pad, transfer, spectra, workers, key=key)


def shift(image: np.ndarray, dx_px: float, dy_px: float) -> np.ndarray:
    """The image moved by (dx, dy) pixels; what enters at an edge is the edge value.

    Pixels are boxes: moving the box grid by a fraction of a pixel shares each pixel's charge among the four
    it now overlaps by area, which is bilinear interpolation (flux-conserving and never negative, unlike a
    spline, which rings by tens of percent around an undersampled bright star)."""
    return ndimage.shift(image, (dy_px, dx_px), order=1, mode="nearest").astype(image.dtype)


def similarity(image: np.ndarray, ys: np.ndarray, xs: np.ndarray, yc: float, xc: float, dx_px: float, dy_px: float,
               rot_deg: float = 0.0, scale: float = 0.0, step: float = 1.0, at: np.ndarray | None = None
               ) -> np.ndarray:
    """The image moved by (dx, dy) [sensor px], rotated by ``rot_deg`` (counter-clockwise in (x, y)) and scaled
    by ``1 + scale`` about the sensor point (xc, yc): the content at ``p`` (from the centre) lands at
    ``(1 + scale) R(rot) p + d``, the similarity transform (4 parameters) a WCS's linear part holds (its
    reference pixel, position angle and plate scale: Calabretta & Greisen 2002, A&A 395 1077, sect. 2.1).

    ``ys``, ``xs`` are the sensor coordinates of the image's pixel centres, ``step`` their spacing (the binning
    of an output image); bilinear as :func:`shift` (the pixel boxes' overlap, never negative). With ``at``
    (flat indices of output pixels) only those are computed (a 1-D array of their values)."""
    if at is None:
        yy, xx = np.meshgrid(ys - yc, xs - xc, indexing="ij")
    else:
        iy, ix = np.divmod(np.asarray(at), image.shape[1])
        yy, xx = ys[iy] - yc, xs[ix] - xc
    c, s = np.cos(np.radians(rot_deg)), np.sin(np.radians(rot_deg))
    u, v = xx - dx_px, yy - dy_px  # the inverse map: each output pixel samples the input there
    src_x = (c * u + s * v) / (1.0 + scale) + xc
    src_y = (-s * u + c * v) / (1.0 + scale) + yc
    return ndimage.map_coordinates(image, [(src_y - ys[0]) / step, (src_x - xs[0]) / step], order=1,
                                   mode="nearest").astype(image.dtype)


#: time sampling of a curved or accelerating drift path [px]: the Gauss-Legendre nodes of
#: :func:`drift_path_transfer` are at most this far apart along the path (far finer than the nodes need: the
#: rule integrates ``exp(-2 pi i f . p(t))`` to ~1e-12 at any frequency of the grid)
DRIFT_PATH_SAMPLING_PX = 0.25


def drift_path_px(t: np.ndarray, dx_px: float, dy_px: float, accel: float = 0.0, sagitta_px: float = 0.0
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The image's displacement (x, y) [px] at the exposure times ``t`` [1] (``t`` in [-1/2, 1/2], 0 at
    mid-exposure) of a drift ``d = (dx, dy)`` [px] with an along-track acceleration and a bow across it.

    The second-order Taylor expansion of the pointing path about mid-exposure, with its time-mean at the
    origin (the drift never moves a centroid; a shift is ``pointing_offset``'s)::

        p(t) = d t + (accel |d| d_hat + 4 sagitta n_hat) (t^2 - 1/12)

    ``d_hat = d / |d|``, ``n_hat = d_hat`` rotated by +90 deg (counter-clockwise from +x in pixel (x, y)
    coordinates: ``(-d_y, d_x) / |d|``). ``accel`` [1] is the along-track quadratic coefficient over
    ``|d|``: the speed along ``d`` is ``|d| (1 + 2 accel t)``, so ``accel = +1`` starts at rest (constant
    acceleration from rest; the source dwells at the start, ``-d/2`` side) and ``-1`` ends at rest; for
    ``|accel| <= 1`` the motion along ``d`` never reverses. ``sagitta`` [px] is the trail's bow across its
    chord, its sign the side of its centre of curvature: the path's acceleration across the track is
    ``8 sagitta n_hat``, so ``sagitta > 0`` turns counter-clockwise (towards ``+n_hat``) all along. The
    path's ends (``t = +-1/2``) both lie ``4 sagitta (1/4 - 1/12) = 2/3 sagitta`` across and mid-exposure
    ``-1/3 sagitta``: a parabola whose vertex stands ``|sagitta|`` from the chord joining its ends (on the
    ``-n_hat`` side for ``sagitta > 0``), for any ``accel`` (the chord is parallel to ``d``).
    ``(d, accel, sagitta)`` and ``(-d, -accel, -sagitta)`` are the same path run backwards (``t -> -t``):
    the same trail. ``d = 0`` has no direction: no motion.
    """
    t = np.asarray(t, float)
    length = float(np.hypot(dx_px, dy_px))
    if length == 0:
        return np.zeros_like(t), np.zeros_like(t)
    ux, uy = dx_px / length, dy_px / length
    qx = accel * length * ux - 4.0 * sagitta_px * uy  # the quadratic coefficient, accel |d| d_hat + 4 s n_hat
    qy = accel * length * uy + 4.0 * sagitta_px * ux
    u = t * t - 1.0 / 12.0
    return dx_px * t + qx * u, dy_px * t + qy * u


def drift_path_transfer(dx_px: float, dy_px: float, accel: float = 0.0, sagitta_px: float = 0.0,
                        dtype=np.complex128):
    """The transfer function ``H(fx, fy)`` [1] (``f`` in cycles/px) of the drift path of
    :func:`drift_path_px`, and the pad [px] a filter with it needs (the path's largest excursion + 2).

    A source that moves along ``p(t)`` while the shutter is open records the time density of the path: the
    kernel is ``k(x) = integral over t of delta(x - p(t)) dt`` (the motion-blur point-spread function,
    Potmesil & Chakravarty 1983, Computer Graphics 17(3) 389, doi:10.1145/800059.801169), whose
    Fourier transform is the time mean of the path's phase factors (the shift theorem, Bracewell, *The
    Fourier Transform and its Applications*, 3rd ed. 2000, ch. 6)::

        H(f) = integral_{-1/2}^{1/2} exp(-2 pi i f . p(t)) dt

    A straight uniform path gives ``sinc(f . d)``. The integral is done by Gauss-Legendre quadrature over
    ``t`` with nodes at most :data:`DRIFT_PATH_SAMPLING_PX` apart along the path (arc length at most
    ``|d| + |q| / 2``, ``q`` the quadratic coefficient): with ``N`` nodes the rule is exact for polynomials
    of degree ``2N - 1``, far beyond the phase's ``pi |p|`` radians at the grid's highest frequency. Each
    node's factor separates, ``exp(-2 pi i fx p_x) exp(-2 pi i fy p_y)``, so ``H`` on the (fy, fx) grid is
    one matrix product ``E_y^T diag(w) E_x`` (a BLAS call, not ``N`` passes over the spectrum).
    ``dtype``: the complex type of ``H`` (complex64 for a float32 image)."""
    length = float(np.hypot(dx_px, dy_px))
    arc = length * (1 + abs(accel) / 2) + 2.0 * abs(sagitta_px)  # |d| + |q| / 2 >= the path's length
    n = max(8, int(np.ceil(arc / DRIFT_PATH_SAMPLING_PX)))
    t, w = np.polynomial.legendre.leggauss(n)
    t, w = t / 2, w / 2  # nodes on [-1/2, 1/2], weights summing to 1
    px, py = drift_path_px(t, dx_px, dy_px, accel, sagitta_px)
    ex, ey = drift_path_px(np.array([-0.5, 0.5]), dx_px, dy_px, accel, sagitta_px)
    pad = int(np.ceil(max(np.max(np.abs(px)), np.max(np.abs(py)), np.max(np.abs(ex)), np.max(np.abs(ey))))) + 2

    def transfer(fx, fy):
        ex_ = np.exp(-2j * np.pi * px[:, None] * np.ravel(fx)[None, :]).astype(dtype)  # (N, nx)
        ey_ = (w[:, None] * np.exp(-2j * np.pi * py[:, None] * np.ravel(fy)[None, :])).astype(dtype)  # (N, ny)
        return ey_.T @ ex_  # (ny, nx): sum over the nodes

    return transfer, pad


def drift_smear(image: np.ndarray, dx_px: float, dy_px: float, accel: float = 0.0, sagitta_px: float = 0.0,
                spectra: dict | None = None, workers: int | None = None) -> np.ndarray:
    """The image smeared along the drift path of :func:`drift_path_px`: what a pointing that drifts by
    ``d = (dx, dy)`` [px] during the exposure records (centred: the nominal pointing is the mid-exposure
    one, and the path's time-mean is the origin, so no centroid moves). Flux conserving; edges are extended
    with their own values.

    ``accel = sagitta_px = 0`` (the default): a uniform drift along the segment from ``-d/2`` to ``+d/2``,
    whose (box) kernel has the transfer function ``H(f) = sinc(f . d)`` (``sinc(u) = sin(pi u) / (pi u)``;
    Bracewell, *The Fourier Transform and its Applications*, 3rd ed. 2000, ch. 6), applied in Fourier space:
    exact for any sub-pixel length and direction, and the output's covariance is the input's plus
    ``d d^T / 12`` (a box of length L has variance L^2 / 12 along it). With ``accel`` [1] (an along-track
    acceleration, in [-1, 1]) or ``sagitta_px`` [px] (a bow across the chord), the second-order path's
    transfer function :func:`drift_path_transfer`; the covariance added is then (along ``d_hat``, across
    ``n_hat``; ``var t = 1/12``, ``var t^2 = 1/180``, ``cov(t, t^2) = 0`` for uniform ``t``)::

        C_along = |d|^2 (1/12 + accel^2 / 180),   C_across = 16 sagitta^2 / 180,
        C_along,across = 4 accel |d| sagitta / 180

    For an undersampled image the band limit rings faintly around sharp peaks (clipped at zero by the
    adapter, as for :func:`blur`). ``spectra``, ``workers``: see :func:`fourier_filter`.
    """
    if dx_px == 0 and dy_px == 0:
        return image.copy()
    if accel == 0 and sagitta_px == 0:
        pad = int(np.ceil(0.5 * max(abs(dx_px), abs(dy_px)))) + 2
        return fourier_filter(image, pad, lambda fx, fy: np.sinc(fx * dx_px + fy * dy_px), spectra, workers,
                              key=("sinc", float(dx_px), float(dy_px)))
    ctype = np.complex128 if image.dtype == np.float64 else np.complex64  # fourier_filter's working precision
    transfer, pad = drift_path_transfer(dx_px, dy_px, accel, sagitta_px, ctype)
    return fourier_filter(image, pad, transfer, spectra, workers,
                          key=("drift_path", float(dx_px), float(dy_px), float(accel), float(sagitta_px)))


def vibration_smear(image: np.ndarray, ax_px: float, ay_px: float, spectra: dict | None = None,
                    workers: int | None = None) -> np.ndarray:
    """The image smeared by a sinusoidal vibration of amplitude vector ``a = (ax, ay)`` [px] during the
    exposure (many periods, or a whole number of them): each source spread over the segment ``-a .. +a``
    with the arcsine density ``1 / (pi sqrt(A^2 - s^2))`` (the image dwells at the turning points), whose
    transfer function is ``J0(2 pi f . a)`` (Wulich & Kopeika 1987, Opt. Eng. 26, 529; Hadar, Fisher &
    Kopeika 1992, Opt. Eng. 31, 581: the high-frequency vibration MTF). Flux conserving; the covariance
    added is ``a a^T / 2`` (the arcsine law's variance A^2 / 2)."""
    if ax_px == 0 and ay_px == 0:
        return image.copy()
    pad = int(np.ceil(max(abs(ax_px), abs(ay_px)))) + 2
    return fourier_filter(image, pad, lambda fx, fy: special.j0(2 * np.pi * (fx * ax_px + fy * ay_px)), spectra,
                          workers, key=("j0", float(ax_px), float(ay_px)))


def one_sided_tail_transfer(tail_px: float, tail_frac: float, angle_deg: float):
    """The transfer function ``H(fx, fy)`` [1] (``f`` in cycles/px) of a PSF with a one-sided tail, and the pad
    [px] a filter with it needs.

    The kernel keeps ``1 - tail_frac`` of each source's light where it is and moves ``tail_frac`` into an
    exponential tail of e-folding length ``tail_px`` [px] along the unit vector ``u`` at ``angle_deg``
    (counter-clockwise from +x), starting at the source: ``k(x) = (1 - f) delta(x) + f delta_perp(x)
    exp(-s / L) / L`` for ``s = x . u >= 0``. Its Fourier transform (Bracewell, *The Fourier Transform and
    its Applications*, 3rd ed. 2000, table of transforms: ``exp(-s/L) H(s) / L <-> 1 / (1 + 2 pi i L f)``)::

        H(f) = 1 - f_tail + f_tail / (1 + 2 pi i L f . u)

    The tail's cumulants along ``u`` (those of the mixture of a point and an exponential of mean L):
    ``k1 = f L``, ``k2 = f L^2 (2 - f)``, ``k3 = 2 f L^3 (3 - 3 f + f^2)``; across ``u`` none. Cumulants of a
    convolution add, so a source's profile gains exactly these (its first moment moves by ``f L``)."""
    f, length = float(tail_frac), float(tail_px)
    ux, uy = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))
    pad = int(np.ceil(8 * length)) + 2  # exp(-8): 3e-4 of the tail beyond the pad

    b = (2j * np.pi * length).imag

    def transfer(fx, fy):
        # (1 - f) + f / (1 + 2 pi i L f.u), the denominator built in place: its real part is 1, its imaginary
        # part 2 pi L f.u (the same numbers as the complex product, without a complex temporary)
        z = np.empty(np.broadcast_shapes(np.shape(fx), np.shape(fy)), np.complex128)
        z.real = 1.0
        np.multiply(fx * ux + fy * uy, b, out=z.imag)
        np.divide(f, z, out=z)
        z += 1.0 - f
        return z

    return transfer, pad


def one_sided_tail(image: np.ndarray, tail_px: float, tail_frac: float, angle_deg: float,
                   spectra: dict | None = None, workers: int | None = None) -> np.ndarray:
    """The image whose every source has ``tail_frac`` [1] of its light in a one-sided exponential tail of
    e-folding length ``tail_px`` [px] along ``angle_deg`` [deg] (:func:`one_sided_tail_transfer`), applied in
    Fourier space (flux conserving; edges extended with their own values).

    A lopsided PSF, whose third moment a symmetric blur or elongation cannot make: the coma of an off-axis
    field point of a paraboloid or of a decentred or tilted mirror (third-order coma: every pupil zone of
    radius rho images as a circle of radius ``A rho^2`` centred ``2 A rho^2`` from the Gaussian image point,
    equal light for equal steps of ``rho^2``, so the patch's light falls monotonically from its apex at the
    Gaussian image point along the tail, ``3 A`` long, ``A = theta f / (16 N^2)`` for a paraboloid with the
    stop at the mirror; Schroeder, *Astronomical Optics*, 2nd ed. 2000, 6.2; Bely, *The Design and
    Construction of Large Optical Telescopes*, Springer 2003, on the coma a decentred secondary or primary
    adds over the whole field), or a one-sided tail of the pointing (a tracking jump, a wind gust, then the
    return). The exponential is the simplest monotonic one-sided profile with the apex at the source: its ``tail_px`` and ``tail_frac`` are effective values
    (geometric coma of a uniform pupil has the along-tail mean ``A`` and variance ``A^2 / 2``).
    ``spectra``, ``workers``: see :func:`fourier_filter`."""
    if tail_frac == 0 or tail_px <= 0:
        return image.copy()
    ctype = np.complex128 if image.dtype == np.float64 else np.complex64
    transfer, pad = one_sided_tail_transfer(tail_px, tail_frac, angle_deg)
    return fourier_filter(image, pad, lambda fx, fy: transfer(fx, fy).astype(ctype, copy=False), spectra, workers,
                          key=("tail", float(tail_px), float(tail_frac), float(angle_deg)))


def displaced_halo_transfer(halo_frac: float, sigma_px: float, dx_px: float, dy_px: float):
    """The transfer function ``H(fx, fy)`` [1] (``f`` in cycles/px) of a PSF that keeps ``1 - halo_frac`` of each
    source's light in its core and spreads ``halo_frac`` over a round Gaussian halo of rms ``sigma_px`` [px]
    per axis centred ``(dx_px, dy_px)`` [px] from it, and the pad [px] a filter with it needs:
    ``k(x) = (1 - f) delta(x) + f N(x; d, sigma^2 I)``, whose Fourier transform is (the shift theorem and the
    Gaussian's transform; Bracewell 2000, ch. 6)::

        H(f) = 1 - f_h + f_h exp(-2 pi^2 sigma^2 |f|^2) exp(-2 pi i f . d)

    The flare of a fast camera lens off its axis: a sharp core and a broad patch of the light the lens's
    residual aberrations (coma, spherochromatism, the out-of-focus colours) spread and displace along the field
    radius (Kingslake & Johnson, *Lens Design Fundamentals*, 2nd ed. 2010, ch. 4: the comatic flare lies to one
    side of the sharp image; Racine 1996, PASP 108, 699: a PSF is a core and a broad aureole). The Gaussian
    gives the flare its first two moments (mean ``d``, variance ``sigma^2``): the share, reach and displacement
    a residual of a few pixels sees. The source's light centroid moves by ``f d``; its light is conserved."""
    f, s = float(halo_frac), float(sigma_px)
    dx, dy = float(dx_px), float(dy_px)
    pad = int(np.ceil(4 * s + max(abs(dx), abs(dy)))) + 2

    def transfer(fx, fy):
        return (1.0 - f) + f * np.exp(-2 * np.pi ** 2 * s * s * (fx * fx + fy * fy)
                                      - 2j * np.pi * (fx * dx + fy * dy))

    return transfer, pad


def tail_cumulants(tail_px: float, tail_frac: float) -> tuple[float, float, float]:
    """The first three cumulants (k1 [px], k2 [px^2], k3 [px^3]) along its direction of the one-sided tail
    kernel of :func:`one_sided_tail_transfer` (a point of weight ``1 - f`` and an exponential of mean ``L``
    and weight ``f``: raw moments ``f L``, ``2 f L^2``, ``6 f L^3``)."""
    f, length = float(tail_frac), float(tail_px)
    return f * length, f * length ** 2 * (2 - f), 2 * f * length ** 3 * (3 - 3 * f + f * f)


def decentering_shift(x, y, p1_per_px: float, p2_per_px: float):
    """Brown's (1966, Photogramm. Eng. 32, 444, eq. 13) decentering displacement (dx, dy) [px] at (x, y) [px]
    from the optical axis: ``dx = p1 (r^2 + 2 x^2) + 2 p2 x y``, ``dy = p2 (r^2 + 2 y^2) + 2 p1 x y``."""
    r2 = x * x + y * y
    return p1_per_px * (r2 + 2 * x * x) + 2 * p2_per_px * x * y, p2_per_px * (r2 + 2 * y * y) + 2 * p1_per_px * x * y


def radial_distortion(image: np.ndarray, ys: np.ndarray, xs: np.ndarray, yc: float, xc: float, k_per_px2: float,
                      step: float = 1.0, p1_per_px: float = 0.0, p2_per_px: float = 0.0,
                      at: np.ndarray | None = None) -> np.ndarray:
    """Image whose content at radius r from (xc, yc) moves to r (1 + k r^2) [px] (k > 0: pincushion), plus
    the decentering (tangential) distortion of Brown (1966, Photogramm. Eng. 32, 444, eq. 13; the
    Brown-Conrady model), with (x, y) measured from the centre:
    ``dx = p1 (r^2 + 2 x^2) + 2 p2 x y``, ``dy = p2 (r^2 + 2 y^2) + 2 p1 x y`` [px] (``p1``, ``p2`` [px^-1]):
    what a lens element decentred or tilted off the axis adds to the radial distortion.

    ``ys``, ``xs`` are the sensor coordinates of the image's pixel centres, ``step`` their spacing (the
    binning of an output image). With ``at`` (flat indices of output pixels) only those are computed (a 1-D
    array of their values)."""
    if at is None:
        yy, xx = np.meshgrid(ys - yc, xs - xc, indexing="ij")
    else:
        iy, ix = np.divmod(np.asarray(at), image.shape[1])
        yy, xx = ys[iy] - yc, xs[ix] - xc
    r2 = xx * xx + yy * yy
    f = 1.0 + k_per_px2 * r2
    # inverse mapping to first order: the output pixel at r' samples the input at r' / (1 + k r'^2), less the
    # decentering displacement there
    src_y, src_x = yy / f, xx / f
    if p1_per_px or p2_per_px:
        dx, dy = decentering_shift(xx, yy, p1_per_px, p2_per_px)
        src_x, src_y = src_x - dx, src_y - dy
    src_y = ((src_y + yc) - ys[0]) / step
    src_x = ((src_x + xc) - xs[0]) / step
    return ndimage.map_coordinates(image, [src_y, src_x], order=1, mode="nearest").astype(image.dtype)


def disc_kernel(radius_px: float) -> np.ndarray:
    """Normalised uniform disc [1] (a defocused ghost) of ``radius_px``, antialiased by 4x supersampling."""
    r = max(float(radius_px), 0.5)
    half = int(np.ceil(r)) + 1
    n, m = 4, 2 * half + 1
    c = (np.arange(m * n) + 0.5) / n - (half + 0.5)  # sub-sample centres, symmetric about 0
    inside = (c[:, None] ** 2 + c[None, :] ** 2) <= r * r
    k = inside.reshape(m, n, m, n).mean(axis=(1, 3))
    return (k / k.sum()).astype(np.float32)


def ghost_image(image: np.ndarray, ys: np.ndarray, xs: np.ndarray, yc: float, xc: float, radius_px: float
                ) -> np.ndarray:
    """Unit-strength ghost: the image reflected through the axis (xc, yc), spread over a disc [same unit].

    Light reflected through the axis from outside the window is not known here and is left out.
    """
    gy = np.rint(2 * yc - ys).astype(int) - int(ys[0])
    gx = np.rint(2 * xc - xs).astype(int) - int(xs[0])
    oky, okx = (gy >= 0) & (gy < image.shape[0]), (gx >= 0) & (gx < image.shape[1])
    mirrored = np.zeros_like(image)
    mirrored[np.ix_(oky, okx)] = image[np.ix_(gy[oky], gx[okx])]
    return signal.oaconvolve(mirrored, disc_kernel(radius_px), mode="same").astype(image.dtype)


def _store(data: np.ndarray, new: np.ndarray) -> None:
    """Write a transformed image back in place, without the tiny negative ringing of splines and FFTs."""
    np.maximum(new, 0, out=data)


def _photo_sensor_coords(tile: Tile) -> tuple[np.ndarray, np.ndarray, float, float]:
    ys, xs = tile.pixel_centres()
    s = tile.sensor
    return ys, xs, (s.sensor_height_px - 1) / 2.0, (s.sensor_width_px - 1) / 2.0


# --- diagnosis: fitted through the transformation itself (Gauss-Newton) ------------------------------------------

def _form_key(sub) -> tuple[int, ...]:
    """A nested form's parameter subset as a hashable key (``TransformSignature.shared``, the memo of
    :meth:`TransformSignature.form_fit`)."""
    return tuple(int(i) for i in sub)


class TransformSignature(Signature):
    """The effect transforms the photo-signal image: ``model' = model + T_theta(P) - P``.

    Started from the first-order (linearised) estimate ``theta_0`` and refined by Gauss-Newton with
    finite-difference Jacobians of the transformation itself, so large blurs and shifts (comparable to the
    PSF) are fitted as well as small ones. Works in output pixels; ``to_params`` converts to the effect's
    parameters (sensor pixels). A ``transform`` that takes ``spectra`` and ``workers`` keywords gets a cache
    of the photo-signal's Fourier transform for the fit and FIT_FFT_WORKERS threads (:func:`fourier_filter`).
    """

    kind = "transform"

    def __init__(self, start, transform, to_params, steps, explain, pattern="", n_iter: int = 6, check=None,
                 nested: list[tuple[int, ...]] | None = None, chain: bool = False,
                 shared: tuple[tuple[int, ...], ...] = (), keep: bool = False):
        self.start, self.transform, self.to_params, self.steps = start, transform, to_params, np.asarray(steps, float)
        self.explain, self.pattern, self.n_iter, self.check = explain, pattern, n_iter, check
        self.nested = nested
        #: ``chain``: each nested subset after the first starts from the previous subset's fitted parameters
        #: (the new ones at 0) and is fitted only when that one was a candidate (its ``to_params`` gave
        #: parameters): a richer form refines a simpler one (a drift's path from its straight trail)
        self.chain = chain
        #: ``shared``: the nested subsets other signatures' nested tests take as their simpler form
        #: (:meth:`form_fit`): fitted once per frame and kept in the residuals' memo; the others are not kept
        #: (each holds a frame-sized map)
        self.shared = frozenset(_form_key(sub) for sub in shared)
        #: ``keep``: the whole fit is kept in the residuals' memo too (one frame-sized map): another signature's
        #: check asks for it (the distortion's asks the pointing offset's) and gets it without a second fit
        self.keep = keep
        self._spectra = {"spectra", "workers"} <= set(inspect.signature(transform).parameters)
        #: a transform that takes ``at`` (flat pixel indices) evaluates only those pixels: the search steps then
        #: cost the sample's size, not the frame's
        self._at = "at" in inspect.signature(transform).parameters

    def fit(self, res, name):
        """The fit of all parameters; with ``nested`` (subsets of the parameters, the others held at 0), the
        subset whose fit has the lowest delta BIC (a simpler form is kept unless the extra terms pay for
        their parameters). With ``keep``, fitted once per frame (a copy of its own returned each time)."""
        if not self.keep:
            return self._fit_all(res, name)
        fit = res.memo(("transform_fit", name), lambda: self._fit_all(res, name))
        # a copy of its own: the caller may drop the copy's maps (a series keeps none) or add to its state
        return None if fit is None else replace(fit, params=dict(fit.params), state=dict(fit.state))

    def _fit_all(self, res, name):
        if not _has_structure(res):
            return None
        if not self.nested:
            fit = self._fit(res, name, self.start, self.transform, self.to_params, self.steps)
            if fit is not None:
                fit.state["transform_sub"] = np.arange(self.steps.size)
            return fit
        best = None
        prev = None  # with ``chain``: the previous subset's fit
        for i, sub in enumerate(self.nested):
            sub = np.asarray(sub, int)
            if self.chain and i > 0:
                if prev is None:
                    break
                start = (lambda r, sub=sub, th0=prev.state["transform_theta"]: th0[sub])
                fit = self._fit_form(res, name, sub, start)
            elif _form_key(sub) in self.shared:  # the nested tests' simpler form: fitted once
                fit = self.form_fit(res, name, sub)
                # a copy of its own: the caller may drop the copy's maps (a series keeps none) or add to its state
                fit = None if fit is None else replace(fit, state=dict(fit.state))
            else:
                fit = self._fit_form(res, name, sub)
            prev = fit
            if fit is not None and (best is None or fit.delta_bic < best.delta_bic):
                best = fit
        return best

    def _fit_form(self, res, name, sub, start=None):
        """The fit of one nested form: the parameters ``sub`` (the others held at 0), started from ``start(res)``
        (default: the signature's own start of that subset)."""
        sub, n_all = np.asarray(sub, int), self.steps.size

        def embed(th):
            full = np.zeros(n_all)
            full[sub] = th
            return full

        if start is None:
            start = (lambda r: _take(self.start(r, sub), sub))
        fit = self._fit(res, name, start, lambda r, photo, th, **kw: self.transform(r, photo, embed(th), **kw),
                        lambda th, r: self.to_params(embed(th), r), self.steps[sub])
        if fit is not None:
            fit.state["transform_theta"] = embed(fit.state["transform_theta"])
            fit.state["transform_sub"] = sub
        return fit

    def form_fit(self, res, name, sub):
        """The fit of the single form ``sub`` (a nested subset, fitted from its own start), cached on ``res``:
        the simpler form a richer one must beat (:func:`_nested_gain`). None when it is no candidate."""
        return res.memo(("form_fit", name, _form_key(sub)),
                        lambda: self._fit_form(res, name, sub) if _has_structure(res) else None)

    def refit(self, fit, res, name):
        """``fit``'s form (its nested subset of the parameters) refitted on the fitted pixels of ``res`` (a
        held-out fold), started from ``fit``'s parameters: as :meth:`LinearSignature.refit` keeps its variant,
        the fold's fit is cross-validated without repeating the form search (the nested forms' choice and the
        starts' linearised estimates, which on half the pixels of a small effect may land on another form or
        another local minimum and score the search's noise, not the effect)."""
        th, sub = fit.state.get("transform_theta"), fit.state.get("transform_sub")
        if th is None or sub is None:
            return self.fit(res, name)
        if not _has_structure(res):
            return None
        th, sub, n_all = np.asarray(th, float), np.asarray(sub, int), self.steps.size

        def embed(t):
            full = np.zeros(n_all)
            full[sub] = t
            return full

        out = self._fit(res, name, lambda r: th[sub].copy(),
                        lambda r, photo, t, **kw: self.transform(r, photo, embed(t), **kw),
                        lambda t, r: self.to_params(embed(t), r), self.steps[sub])
        if out is not None:
            out.state.update(transform_theta=embed(out.state["transform_theta"]), transform_sub=sub)
        return out

    def _fit(self, res, name, start, transform, to_params, steps):
        # Gauss-Newton on the search subsample of the fitted pixels, with the global levels refitted at every
        # step (detector.signatures.fit_linear / profiled_chi2); the result is evaluated on every fitted pixel
        ctx = search_sample(res)
        sidx, sr, sw = ctx["idx"], ctx["r"], ctx["w"]
        # transform the photo-signal before the full-well clip, then clip as the chain does
        photo = np.asarray(res.photo_field, np.float64)
        cap = res.sensor.full_well_e * res.pixel_sum / res.gain
        clipped = np.minimum(photo, cap)
        theta = start(res)
        if theta is None:
            return None

        spectra: dict = {}
        kw = {"spectra": spectra, "workers": FIT_FFT_WORKERS} if self._spectra else {}

        last: dict = {}  # the last evaluation (a Gauss-Newton step's base is the previous step's accepted trial)
        # the accepted parameters' evaluation (the start's, then each accepted trial's): the fit ends on it, after
        # Jacobian columns and rejected trials have replaced ``last``, and its whole image is not transformed again
        accepted: dict = {}

        def image(th):
            key = np.asarray(th, float).tobytes()
            for ev in (last, accepted):
                if ev.get("theta") == key and ev["full"] is not None:
                    return np.minimum(ev["full"], cap)
            return np.minimum(transform(res, photo, th, **kw), cap)

        def on_sample(th):
            """The transformed, clipped image at the search sample's pixels only (what the steps use); the
            whole transformed image is kept unclipped (clipped by :func:`image` when it is asked for)."""
            key = np.asarray(th, float).tobytes()
            if last.get("theta") != key:
                if self._at:
                    full, values = None, np.minimum(transform(res, photo, th, at=sidx, **kw), cap)
                else:
                    full = transform(res, photo, th, **kw)
                    values = np.minimum(full.ravel()[sidx], cap)
                last.update(theta=key, full=full, values=values)
            return last["values"]

        clipped_s = clipped.ravel()[sidx]

        def chi2_of(th):
            return profiled_chi2(res, sidx, sr - (on_sample(th) - clipped_s), sw)

        best = chi2_of(theta)
        accepted.update(last)
        for _ in range(self.n_iter):
            base = on_sample(theta)
            jac = np.stack([(on_sample(theta + h * e) - base) / h for h, e in zip(steps, np.eye(theta.size))])
            # fit_linear asks for the templates at (chunks of) the sample's pixels: their positions in it
            step, _ = fit_linear(res, lambda i, jac=jac: jac[:, np.searchsorted(sidx, i)], sidx,
                                 sr - (base - clipped_s), sw)
            lam, improved = 1.0, False
            # halve the step down to 1e-3 of it, but not below the convergence tolerance (a shorter step would
            # end the fit anyway: it is not worth a transform of the frame)
            while lam > 1e-3 and not np.all(np.abs(lam * step) < 1e-3 * steps):
                trial = theta + lam * step
                c = chi2_of(trial)
                if c < best:
                    theta, best, improved = trial, c, True
                    accepted.update(last)
                    break
                lam /= 2
            if not improved or np.all(np.abs(lam * step) < 1e-3 * steps):
                break
        params = to_params(theta, res)
        if params is None:
            return None
        idx, _, w = res.flat_profiled()
        r = res.flat()[1]
        delta = (image(theta) - clipped).astype(np.float32)
        d = profiled_chi2(res, idx, r - delta.ravel()[idx], w) - res.chi2_profiled()
        return Fit(name, params, d, theta.size, res.n_fit, self.explain(params, res), delta_adu=delta,
                   state={"transform_theta": np.array(theta, float)})


def _take(theta, sub):
    """``theta[sub]`` (a start that already returns the subset's values is passed through); None stays None."""
    if theta is None:
        return None
    theta = np.asarray(theta, float)
    return theta if theta.size == len(sub) else theta[sub]


def _derivatives(res) -> dict:
    """First and second derivatives of the model's photo-signal image [ADU / output px^n], cached."""
    cached = res._flat.get("image_plane_derivatives")
    if cached is None:
        p = res.photo_adu.astype(np.float64)
        gy, gx = np.gradient(p)
        gyy, gyx = np.gradient(gy)
        gxy, gxx = np.gradient(gx)
        cached = {"x": gx, "y": gy, "xx": gxx, "yy": gyy, "xy": 0.5 * (gxy + gyx)}
        res._flat["image_plane_derivatives"] = cached
    return cached


def _third_derivatives(res) -> list[np.ndarray]:
    """Third derivatives (xxx, xxy, xyy, yyy) of the model's photo-signal image [ADU / output px^3], cached."""
    cached = res._flat.get("image_plane_third_derivatives")
    if cached is None:
        d = _derivatives(res)
        gxxy, gxxx = np.gradient(d["xx"])
        gyyy, gyyx = np.gradient(d["yy"])
        cached = [gxxx, gxxy, gyyx, gyyy]
        res._flat["image_plane_third_derivatives"] = cached
    return cached


def _has_structure(res) -> bool:
    """Image-plane effects need sources: a flat screen or a dark (even a vignetted one: its gradients are far
    wider than any blur or shift) has nothing to move or blur. Sources are what a 7 x 7 box average does
    not keep (a high-pass) well above the noise. Kept with the residuals (every transform's fit, form and
    held-out refit asks it of the same photo-signal and variance)."""
    def test() -> bool:
        p = np.asarray(res.photo_field, np.float32)  # before the response (a CFA)
        if not p.size:
            return False
        hp = p - ndimage.uniform_filter(p, 7, mode="nearest")
        return float(np.ptp(hp)) > 10 * float(np.sqrt(np.median(res.var_adu2)))
    return res.memo("image_plane_has_structure", test)


def _max_var(res) -> float:
    """The largest blur variance [output px^2] a fit may try: the parameters' bound of 50 sensor px rms (a
    runaway Gauss-Newton step would otherwise ask for a Fourier transform of a padded frame of GBs)."""
    return (50.0 / res.sensor.binning) ** 2


def _linear_start(res, names: list[str], scale: list[float]) -> np.ndarray:
    """First-order estimate from the derivative templates (heat-equation / Taylor linearisation), cached: the
    second-moment one starts jitter (both its forms), the drift and the elongation."""
    key = ("linear_start", tuple(names), tuple(scale))
    if key not in res._flat:
        d = _derivatives(res)
        ctx = search_sample(res)
        res._flat[key], _ = fit_linear(res, lambda i: np.stack([s_ * d[n].ravel()[i] for n, s_ in zip(names, scale)]),
                                       ctx["idx"], ctx["r"], ctx["w"])
    return np.array(res._flat[key])


def _sensor_centre(res) -> tuple[float, float]:
    s = res.sensor
    return (s.sensor_height_px - 1) / 2.0, (s.sensor_width_px - 1) / 2.0


# blur: theta = (sigma^2 [output px^2], halo fraction [1], halo sigma^2 [output px^2]); three forms (nested): a
# round Gaussian blur of the whole image; a scattering halo (a share of every source's light in a wide Gaussian
# about it, the rest left in place: the far wings micro-roughness and dust scatter, Racine 1996 PASP 108 699);
# and a round core and its wings together (a seeing or defocus profile with wings: Moffat 1969, A&A 3 455). An
# elongated core is not fitted as a blur: alone it is jitter's Gaussian form, the same image, and with wings it
# is the elongated PSF psf_elongation names (astigmatism, a tilted detector, wind shake); what a round blur has
# that a smear of the pointing cannot is its wings
#: halo widths [output px^2] the halo's start is chosen from (by its linear fit: a share of the light moved)
HALO_START_VAR = (4.0, 16.0, 64.0)
#: the largest share of the light a halo (or a one-sided tail, TAIL_MAX_FRAC) may hold: the source's core, the
#: scene's PSF, holds most of it (EXPLAINS_MOST); beyond, the source itself is the wide part, more wings than core
HALO_MAX_FRACTION = 1.0 - EXPLAINS_MOST


def _blur_start(res, sub=(0,)):
    if tuple(sub) == (0,):
        c = _linear_start(res, ["xx", "yy"], [0.5, 0.5])
        return np.array([max(float(np.mean(c)), 0.05)])
    if tuple(sub) == (0, 1, 2):
        return _blur_core_halo_start(res)
    # the halo: its share of the light fitted linearly at each trial width, the best width kept
    ctx = search_sample(res)
    photo = np.asarray(res.photo_field, np.float64)
    best = None
    for h2 in HALO_START_VAR:
        t = (blur(photo, float(np.sqrt(h2))) - photo).ravel()
        coef, d = fit_linear(res, lambda i, t=t: t[i][None, :], ctx["idx"], ctx["r"], ctx["w"])
        f = float(coef[0])
        if 0 < f < HALO_MAX_FRACTION and (best is None or d < best[0]):
            best = (d, f, h2)
    return None if best is None else np.array([best[1], best[2]])


def _blur_core_halo_start(res):
    """The round core and its wings together: the core's second moments (xx + yy template: the heat equation's
    linearisation) fitted linearly with the halo's template at each trial width, the best width kept.

    None (the form not fitted) when the round core alone is no candidate (:meth:`TransformSignature.form_fit`
    of ``(0,)``, the shared form already fitted): second moments of a convolution add, so the core of a core
    with wings is the sources' whole widening less its wings' share ``f h^2``, which is less than the core
    alone finds; a core alone that does not widen the sources (``sigma^2 <= 0``) leaves the joint form's core
    outside its range too (``_blur_params`` refuses ``sigma^2 < 0``), and its fit, a frame's worth of Fourier
    transforms at every step, would end refused."""
    if PSFBlur.signature.form_fit(res, PSFBlur.name, (0,)) is None:
        return None
    ctx = search_sample(res)
    d = _derivatives(res)
    photo = np.asarray(res.photo_field, np.float64)
    core = (0.5 * (d["xx"] + d["yy"])).ravel()
    best = None
    for h2 in (1.0, *HALO_START_VAR):  # and a halo of one pixel: the near wings of a Moffat or exponential profile
        t = (blur(photo, float(np.sqrt(h2))) - photo).ravel()
        coef, chi2 = fit_linear(res, lambda i, t=t: np.stack([core[i], t[i]]), ctx["idx"], ctx["r"], ctx["w"])
        f = float(coef[1])
        if 0 < f < HALO_MAX_FRACTION and (best is None or chi2 < best[0]):
            best = (chi2, coef, h2)
    if best is None:
        return None
    c, h2 = best[1], best[2]
    return np.array([max(float(c[0]), 0.05), float(c[1]), h2])


def _blur_transform(res, photo, th, spectra=None, workers=None):
    s2 = float(np.clip(th[0], 0.0, _max_var(res)))
    out = blur(photo, float(np.sqrt(s2)), spectra=spectra, workers=workers)
    f = float(th[1]) if len(th) > 1 else 0.0
    if f:
        h = float(np.sqrt(np.clip(th[2], 0.0, _max_var(res))))
        # the halo's pad rounded up to a power of two: the fit's steps in its width reuse one padded spectrum
        # (the spectra cache holds the photo-signal's: only when the core is not blurred too)
        pad = 1 << int(np.ceil(np.log2(int(np.ceil(4 * h)) + 1)))
        wide = blur(out, h, spectra=spectra if s2 == 0 else None, workers=workers, min_pad=pad)
        out = (1 - f) * out + f * wide
    return out


def _blur_params(th, res):
    s2 = float(th[0])
    f, h2 = (float(th[1]), float(th[2])) if len(th) > 1 else (0.0, 0.0)
    b = res.sensor.binning
    if f == 0:
        return {"sigma_px": round(float(np.sqrt(s2)) * b, 4)} if 0 < s2 < 100 else None
    if not (0 <= s2 < 100 and 0 < f < HALO_MAX_FRACTION and 0 < h2 < _max_var(res)):
        return None
    return {"sigma_px": round(float(np.sqrt(s2)) * b, 4), "halo_frac": round(f, 5),
            "halo_sigma_px": round(float(np.sqrt(h2)) * b, 4)}


def _blur_words(p, res) -> str:
    if p.get("halo_frac"):
        core = f"; their core wider by {p['sigma_px']:.3g} px rms" if p.get("sigma_px") else ""
        return (f"sources with far wings the model lacks: {100 * p['halo_frac']:.3g} % of their light in a halo of "
                f"{p['halo_sigma_px']:.3g} px rms (scattered light: mirror micro-roughness, dust){core}")
    return f"sources wider than the model, as by an extra Gaussian of {p['sigma_px']:.3g} px rms: PSF blur (focus, seeing)"


#: the nested likelihood-ratio test's bar (Wilks 1938): a richer form adds to the simpler one it nests when it
#: removes, beyond it, a chi2 this many standard deviations above the mean of chi2 with k degrees of freedom,
#: its k extra parameters (mean k, variance 2 k; :func:`detector.significance.nested_gain_significant`), at the
#: STRUCTURE_SIGMA bar of a whole frame's structure: jitter, a drift or an elongation against the round blur
#: they nest, a tail against a shift and blur, an offset against one varying across the field or skewed, a
#: distortion against the similarity transform (:func:`_distortion_check`)
NESTED_SIGMA = STRUCTURE_SIGMA

# the forms nest: a round smear is a blur, an elongated one (jitter, a vibration, a drift's trail, a narrowing
# across: psf_elongation) adds to it, and a lopsided one (a tail) adds odd moments to a shift and a symmetric
# change. A richer form is proposed only when it beats the simpler form it reduces to by the nested
# likelihood-ratio test (:func:`detector.significance.nested_gain_significant`, NESTED_SIGMA): no design floor
# on a length, an axis ratio or a share decides between them, the frame's own evidence does.


def _nested_gain(fit, simpler) -> tuple[float, int]:
    """(chi2 gain, extra parameters) of ``fit`` over the ``simpler`` form's fit (the same fitted pixels, levels
    profiled), or over the model itself (the identity, no parameters) when ``simpler`` is None."""
    if simpler is None:
        return -float(fit.delta_m2lnl), int(fit.k)
    return float(simpler.delta_m2lnl - fit.delta_m2lnl), int(fit.k - simpler.k)


def _beyond_blur(fit, res) -> tuple[float, int]:
    """The nested gain of a smear (jitter, a vibration, a drift, an elongation) over the round blur it reduces
    to when it is short or round: psf_blur's one-parameter core fitted on the same pixels."""
    return _nested_gain(fit, PSFBlur.signature.form_fit(res, "psf_blur", (0,)))


def _linear_gain(res, simple: list, extra: list) -> float:
    """chi2 (search sample, levels profiled) the templates ``extra`` remove beyond ``simple`` (first-order
    templates: images at the full frame's pixels), both fitted linearly: the nested test's gain of a form at
    its linearised start, where its full fit is not yet made."""
    ctx = search_sample(res)
    idx, r, w = ctx["idx"], ctx["r"], ctx["w"]
    _, d_simple = fit_linear(res, lambda i: np.stack([t.ravel()[i] for t in simple]), idx, r, w)
    _, d_both = fit_linear(res, lambda i: np.stack([t.ravel()[i] for t in simple + extra]), idx, r, w)
    return float(d_simple - d_both)


def _smear_elongated(res) -> bool:
    """Whether the sources' second-moment change is significantly anisotropic (cached): the templates of a
    general covariance (xx, yy, xy) against the round blur's Laplacian (2 extra parameters), linearised."""
    def test():
        d = _derivatives(res)
        return nested_gain_significant(_linear_gain(res, [d["xx"] + d["yy"]], [d["xx"] - d["yy"], d["xy"]]), 2,
                                       NESTED_SIGMA)

    return res.memo("smear_elongated", test)


# jitter: theta = (c_xx, c_yy, c_xy) [output px^2]
#: sigma_major / sigma_minor below which a fitted Gaussian smear is named a blur (psf_blur), even when its
#: elongation passes the nested test: a ratio of 1 + SCALE_TOLERANCE is one axis sqrt(1 + SCALE_TOLERANCE) wider
#: and the other as much narrower than round, each within the width a scene knows its PSF to (the policy's
#: psf_width_tolerance, 4.9 %), so a rounder smear is a width, not a shape. Strong frames resolve such ratios: on
#: truth chi2 1e5-1e6 the nested test measures axis ratios of 0.94-0.96 for round kernels (a chi2 gain of ~2500
#: over the round blur, psf_blur-2763062600716554132), which the held-out scores cannot tell from the blur
JITTER_MIN_ELONGATION = 1.0 + SCALE_TOLERANCE


def _jitter_start(res, terms=(0, 1, 2)):
    """theta = (c_xx, c_yy, c_xy [output px^2], a_x, a_y [output px]): the Gaussian smear's covariance from
    the linearised fit; a vibration's amplitude along the major axis from it (arcsine variance A^2 / 2). The
    vibration form is fitted only when the linearised smear is significantly elongated (:func:`_smear_elongated`):
    a round smear has no axis to vibrate along."""
    c = _linear_start(res, ["xx", "yy", "xy"], [0.5, 0.5, 1.0])
    cov = np.array([max(c[0], 0.05), max(c[1], 0.05), c[2]])
    w, ang = _jitter_axes(cov)
    amp = float(np.sqrt(2 * max(w[1], 0.05)))
    if tuple(terms) == (3, 4) and not _smear_elongated(res):
        return None  # no elongated smear to start from: the vibration form is not fitted
    return np.concatenate([cov, amp * np.array([np.cos(np.radians(ang)), np.sin(np.radians(ang))])])


def _jitter_axes(th):
    w, v = np.linalg.eigh(np.array([[th[0], th[2]], [th[2], th[1]]]))
    return w, float(np.degrees(np.arctan2(v[1, 1], v[0, 1]))) % 180.0


def _jitter_transform(res, photo, th, spectra=None, workers=None):
    th = np.asarray(th, float)
    out = photo
    if np.any(th[:3]):
        w, ang = _jitter_axes(th)
        w = np.clip(w, 0.0, _max_var(res))
        out = blur(out, float(np.sqrt(w[1])), float(np.sqrt(w[0])), ang, spectra=spectra, workers=workers)
        spectra = None  # the cached spectrum is the unsmeared image's
    if th.size > 3 and np.any(th[3:5]):
        a = np.clip(th[3:5], -400, 400)
        out = vibration_smear(out, float(a[0]), float(a[1]), spectra=spectra, workers=workers)
    # negatives clipped as the adapter does (_store): the arcsine's horns ring around undersampled (and far
    # saturated) sources, and a fit that keeps what the rendering clips finds a wrong amplitude and direction
    return np.maximum(out, 0)


def _jitter_params(th, res):
    th = np.asarray(th, float)
    b = res.sensor.binning
    if th.size > 3 and np.any(th[3:5]):  # the vibration form (nested: fitted alone, the Gaussian at 0)
        amp = float(np.hypot(th[3], th[4]))
        if not 0 < amp <= 50 / b:
            return None
        ang = float(np.degrees(np.arctan2(th[4], th[3]))) % 180.0
        return {"sigma_major_px": 0.0, "sigma_minor_px": 0.0, "angle_deg": round(ang, 2),
                "vibration_px": round(amp * b, 4)}
    w, ang = _jitter_axes(th)
    # a smear along one line has a minor variance of 0. The transform renders a negative minor variance as 0
    # (a smear cannot narrow), so below 0 the fit's chi2 is flat in it and the fitted value is wherever the
    # steps left it, not a measurement: the minor axis is the line's 0. Whether the sources are narrower across
    # is the elongation's fit to say (it renders a narrowing), and the judge compares the two on held-out pixels
    if w[1] <= 0 or w[1] >= 100:
        return None
    w0 = max(float(w[0]), 0.0)
    # an isotropic smear is psf_blur (nested in this model): whether it is elongated is :func:`_jitter_check`'s
    # nested test; one rounder than JITTER_MIN_ELONGATION is named a blur however significant
    if w[1] < JITTER_MIN_ELONGATION ** 2 * w0:
        return None
    return {"sigma_major_px": round(float(np.sqrt(w[1])) * b, 4), "sigma_minor_px": round(float(np.sqrt(w0)) * b, 4),
            "angle_deg": round(ang, 2)}


def _jitter_check(fit, res) -> str:
    """A smear is jitter only when it beats the round blur it nests (a round jitter is psf_blur; a vibration of
    small amplitude is a Gaussian smear along its axis, whose round part is the blur): the nested test of the
    jitter's fit against psf_blur's core on the same pixels."""
    gain, k = _beyond_blur(fit, res)
    if k < 1 or nested_gain_significant(gain, k, NESTED_SIGMA):
        return ""
    return (f"the smear is round within the noise: its {k} parameters beyond a round blur remove {gain:.3g} chi2, "
            "no more than chance does: a blur (psf_blur), not an elongated jitter")


def _jitter_words(p, res) -> str:
    if p.get("vibration_px", 0.0):
        # a motion shorter end to end than the PSF's FWHM changes the sources' profiles only at the fourth moment
        # (a box, an arcsine and a Gaussian of one variance: (pi f L)^4 terms), which the vibration's form, one
        # parameter fewer than an elongated Gaussian's, wins by its price alone: its words claim a line, no law
        span = 2 * p["vibration_px"]
        if span < psf_fwhm_px(res) * res.sensor.binning:
            return (f"sources smeared along {p['angle_deg']:.0f} deg, {span:.3g} px end to end: image motion along "
                    "one line (a vibration's arcsine profile fits best; a motion shorter than the PSF's FWHM does "
                    "not tell it from a drift's uniform trail or a random smear)")
        return (f"sources smeared back and forth along {p['angle_deg']:.0f} deg, {p['vibration_px']:.3g} px either "
                "way, brightest at both ends (an arcsine profile): a sinusoidal vibration of the pointing (a "
                "drive or wind resonance), not a one-way drift")
    # an elongated Gaussian blur is what random image motion makes and what a static elongated PSF wider both ways
    # makes (astigmatism, a tilted detector: psf_elongation's form is the one narrower across): one frame's
    # sources do not tell the two causes apart, the words say so
    return (f"sources smeared along {p['angle_deg']:.0f} deg, {p['sigma_major_px']:.3g} x {p['sigma_minor_px']:.3g} "
            "px rms: pointing jitter, or a PSF elongated and wider both ways (astigmatism, a tilted detector), "
            "which the sources of one frame do not tell apart")


# elongation: theta = (c_xx, c_yy, c_xy) [output px^2], one eigenvalue negative (narrower across: a smear's
# covariance with its minor eigenvalue freed below 0, so the jitter's Gaussian form is its nested point)
#: highest gain of the narrowing filter (the smooth image a PSF makes holds no power where it would matter)
ELONGATION_MAX_GAIN = 50.0


def _elongation_start(res, terms=(0, 1, 2)):
    """theta = (c_xx, c_yy, c_xy [output px^2], a_x, a_y [output px], f [1]): the symmetric form from the
    linearised second moments, the lopsided (tail) form from the linearised cumulants (:func:`_tail_start`)."""
    if tuple(terms) == (3, 4, 5):
        return _tail_start(res)
    return _linear_start(res, ["xx", "yy", "xy"], [0.5, 0.5, 1.0])


def _elongation_transform(res, photo, th, spectra=None, workers=None):
    th = np.asarray(th, float)
    if th.size > 3 and np.any(th[3:6]):  # the lopsided form (nested: fitted alone, the covariance at 0)
        length = float(np.clip(np.hypot(th[3], th[4]), 0.0, TAIL_MAX_FIT_PX))
        frac = float(np.clip(th[5], 0.0, 1.0))
        ang = float(np.degrees(np.arctan2(th[4], th[3])))
        # negatives clipped as the adapter does (_store): the line kernel rings faintly around sharp sources
        return np.maximum(one_sided_tail(photo, length, frac, ang, spectra=spectra, workers=workers), 0)
    cov = np.array([[th[0], th[2]], [th[2], th[1]]])
    w, v = np.linalg.eigh(cov)
    cov = v @ np.diag(np.clip(w, -_max_var(res), _max_var(res))) @ v.T
    return gaussian_filter_cov(photo, cov, max_gain=ELONGATION_MAX_GAIN, spectra=spectra, workers=workers)


def _elongation_params(th, res):
    th = np.asarray(th, float)
    if th.size > 3 and np.any(th[3:6]):
        return _tail_params(th[3:6], res)
    w, _ = _jitter_axes(th)
    if w[1] <= 0 or w[0] >= 0 or max(w[1], -w[0]) >= 100:
        return None  # a pure blur (or a pure narrowing: a PSF too wide everywhere) is not an elongation
    b2 = res.sensor.binning ** 2
    if np.max(np.abs(th)) * b2 > 25:  # ElongationParams' bounds [sensor px^2]
        return None
    return {"dcxx_px2": round(float(th[0]) * b2, 5), "dcyy_px2": round(float(th[1]) * b2, 5),
            "dcxy_px2": round(float(th[2]) * b2, 5)}


def _elongation_words(p, res) -> str:
    if p.get("tail_frac", 0.0):
        return (f"sources lopsided: {100 * p['tail_frac']:.2g} % of their light in a one-sided tail of "
                f"{p['tail_px']:.3g} px towards {p['tail_angle_deg']:.0f} deg, their cores in place: an asymmetric "
                "PSF (coma of an off-axis point or of a decentred or tilted mirror, a one-sided tracking "
                "tail), which the scene's symmetric PSF lacks")
    w, ang = _jitter_axes(np.array([p["dcxx_px2"], p["dcyy_px2"], p["dcxy_px2"]]))
    return (f"sources wider than the model along {ang:.0f} deg (+{w[1]:.3g} px^2) and narrower across "
            f"({w[0]:.3g} px^2): an elongated PSF (astigmatism, tilt, wind shake), which the scene's round PSF "
            "lacks")


# the lopsided form of the elongation: theta = (a_x, a_y [output px], f [1]), the tail L u = a, its share f
#: longest tail [output px] a fit may try (a runaway step would pad the frame by 8 L)
TAIL_MAX_FIT_PX = 50.0
#: share of the light in the tail above which a tail is not plausible: the source would be more tail than core,
#: which no coma short of a grossly misaligned mirror makes (and there the scene's PSF itself is wrong): the
#: halo's bar, HALO_MAX_FRACTION (a source is more core than wings)
TAIL_MAX_FRAC = HALO_MAX_FRACTION
#: tail length [in PSF FWHM] above which a tail is not plausible: a coma flare or a tracking tail as long as a
#: trail (TRAIL_MIN_FWHM) is a trail (pointing_drift) or a PSF the scene's optics must model, not a correction of it
TAIL_MAX_FWHM = TRAIL_MIN_FWHM
#: share of the light the linearised start assumes when the cumulants cannot tell it
TAIL_START_FRAC = 0.3


def _cumulant_start(res) -> np.ndarray:
    """The linearised change of the sources' first three cumulants, cached: the residual fitted with
    ``-k1 . grad I + 1/2 k2 : grad^2 I - 1/6 k3 : grad^3 I`` (the Edgeworth / Gram-Charlier expansion of a
    convolution with a kernel of cumulants k_n; Kendall & Stuart vol. 1 sect. 6.17). Returns (k_x, k_y,
    k_xx, k_yy, k_xy, k_xxx, k_xxy, k_xyy, k_yyy) [output px^n]."""
    key = "cumulant_start"
    if key not in res._flat:
        d = _derivatives(res)
        odd = _third_derivatives(res)
        temps = [d["x"], d["y"], d["xx"], d["yy"], d["xy"]] + list(odd)
        scale = [-1.0, -1.0, 0.5, 0.5, 1.0, -1 / 6, -1 / 2, -1 / 2, -1 / 6]
        ctx = search_sample(res)
        res._flat[key], _ = fit_linear(res, lambda i: np.stack([s_ * t.ravel()[i] for t, s_ in zip(temps, scale)]),
                                       ctx["idx"], ctx["r"], ctx["w"])
    return np.array(res._flat[key], float)


def _tail_start(res):
    """(a_x, a_y, f) of the tail whose cumulants match the linearised ones (:func:`tail_cumulants`): its
    direction is that of the third cumulant (for a kernel along ``u``, ``k3 u u u``, whose spin-1 part
    ``(k_xxx + k_xyy) + i (k_xxy + k_yyy)`` is ``k3 e^{i angle}``), L and f from ``k3 / k1 = 2 L^2 (3 - 3 f
    + f^2)`` and ``k1 = f L`` along it (or from k2 when the centroid did not move forwards: a pointing offset
    besides the tail). None when the sources are not lopsided (:func:`_sources_lopsided`: a short tail is a
    shift and a blur of the core)."""
    if not _sources_lopsided(res):
        return None
    k = _cumulant_start(res)
    z = complex(k[5] + k[7], k[6] + k[8])
    k3, ang = abs(z), float(np.angle(z))
    if k3 <= 0:
        return None
    c, s_ = np.cos(ang), np.sin(ang)
    k1 = k[0] * c + k[1] * s_
    k2 = k[2] * c * c + k[3] * s_ * s_ + 2 * k[4] * c * s_
    f = TAIL_START_FRAC
    length = float(np.cbrt(k3 / (2 * f * (3 - 3 * f + f * f))))
    for _ in range(20):
        g = 3 - 3 * f + f * f
        if k1 > 0:
            length = float(np.sqrt(k3 / (2 * k1 * g)))
            f = k1 / length
        elif k2 > 0:
            length = float(k3 * (2 - f) / (2 * k2 * g))
            f = 1 - float(np.sqrt(max(1 - k2 / length ** 2, 0.0)))
        f = float(np.clip(f, 0.05, 0.8))
    length = float(np.clip(length, 0.0, TAIL_MAX_FIT_PX / 2))
    if length <= 0:
        return None
    return np.array([length * c, length * s_, f])


def _sources_lopsided(res) -> bool:
    """Whether the sources' third moments changed significantly (cached): the skew templates (the image's third
    derivatives, ``-1/6 k3 : grad^3 I``) beyond a shift and a symmetric second-moment change (the image's first
    and second derivatives), linearised: the nested test of the lopsided form against the shift plus blur a
    sub-pixel tail reduces to (4 extra parameters)."""
    def test():
        d = _derivatives(res)
        gain = _linear_gain(res, [d["x"], d["y"], d["xx"], d["yy"], d["xy"]], list(_third_derivatives(res)))
        return nested_gain_significant(gain, 4, NESTED_SIGMA)

    return res.memo("sources_lopsided", test)


def _tail_params(th, res):
    b = res.sensor.binning
    length, frac = float(np.hypot(th[0], th[1])), float(th[2])
    if not 0.01 <= frac <= 1.0 or not 0 < length * b <= 50 or length > TAIL_MAX_FIT_PX:
        return None  # ElongationParams' bounds: no tail, or one the fit ran away with
    ang = float(np.degrees(np.arctan2(th[1], th[0])))
    return {"dcxx_px2": 0.0, "dcyy_px2": 0.0, "dcxy_px2": 0.0, "tail_px": round(length * b, 4),
            "tail_frac": round(frac, 4), "tail_angle_deg": round(ang, 2)}


def psf_fwhm_px(res) -> float:
    """The model's PSF FWHM [output px], from its photo-signal's derivatives: for a Gaussian of rms sigma,
    ``sum |grad I|^2 / sum (lap I)^2 = sigma^2 / 2`` (Parseval: ``int 4 pi^2 k^2 |G|^2 / int 16 pi^4 k^4
    |G|^2`` with ``|G|^2 = exp(-4 pi^2 sigma^2 k^2)``), summed over the frame (the brightest sources weigh
    most; a smooth background adds almost nothing). Pixel differences underestimate the derivatives of an
    undersampled source, so this errs wide: a plausibility bound, not a measurement."""
    d = _derivatives(res)
    g2 = float(np.sum(d["x"] ** 2 + d["y"] ** 2))
    l2 = float(np.sum((d["xx"] + d["yy"]) ** 2))
    if l2 <= 0:
        return float("inf")
    return 2 * np.sqrt(2 * np.log(2)) * float(np.sqrt(2 * g2 / l2))


def _elongation_check(fit, res) -> str:
    """The symmetric form must be narrower across than any smear makes: it beats the jitter's Gaussian form
    (its nested point, the minor eigenvalue held at 0: one parameter freed) by the nested test, or, without a
    jitter fit, the round blur (two parameters). The lopsided form must be a tail a PSF can have: at most
    TAIL_MAX_FRAC of the light, at most TAIL_MAX_FWHM PSF widths long."""
    p = fit.params
    if not p.get("tail_frac", 0.0):
        smear = Jitter.signature.form_fit(res, "jitter", (0, 1, 2))
        gain, k = (_nested_gain(fit, smear)[0], 1) if smear is not None else _beyond_blur(fit, res)
        if k < 1 or nested_gain_significant(gain, k, NESTED_SIGMA):
            return ""
        return (f"the narrowing across is within the noise: freeing it beyond a smear removes {gain:.3g} chi2 "
                f"({k} parameter{'s' if k > 1 else ''}): a blur or a jitter (psf_blur, jitter), not an elongation")
    if p["tail_frac"] > TAIL_MAX_FRAC:
        return (f"{100 * p['tail_frac']:.2g} % of the sources' light in the tail: a source that is more tail than "
                "core is not a PSF with coma; a trail (pointing_drift) or a wholly different PSF")
    fwhm = psf_fwhm_px(res) * res.sensor.binning
    if p["tail_px"] > TAIL_MAX_FWHM * fwhm:
        return (f"a tail of {p['tail_px']:.3g} px, {p['tail_px'] / fwhm:.2g} times the PSF's FWHM ({fwhm:.3g} px): "
                "a flare that long is a trail (pointing_drift) or a PSF the optics must model, not a coma tail")
    return ""


# offset: theta = (dx, dy [output px], rotation [deg], plate-scale change [1]); nested and chained: the rigid
# shift first, then the similarity transform started from it
def _offset_start(res, sub=(0, 1)):
    return np.concatenate([_linear_start(res, ["x", "y"], [-1.0, -1.0]), [0.0, 0.0]])


def _offset_transform(res, photo, th, at=None):
    th = np.asarray(th, float)
    b = res.sensor.binning
    rot = float(np.clip(th[2], -10.0, 10.0)) if th.size > 2 else 0.0  # OffsetParams' bounds: the fit sees them
    sc = float(np.clip(th[3], -0.05, 0.05)) if th.size > 3 else 0.0
    if rot == 0.0 and sc == 0.0 and at is None:
        return shift(photo, float(th[0]), float(th[1]))
    yc, xc = _sensor_centre(res)
    return similarity(photo, res.ys, res.xs, yc, xc, float(th[0]) * b, float(th[1]) * b, rot, sc, step=b, at=at)


def _field_radius(res) -> float:
    """The largest distance [sensor px] of the window's pixels from the sensor centre."""
    yc, xc = _sensor_centre(res)
    return float(np.sqrt(max((res.ys - yc) ** 2) + max((res.xs - xc) ** 2)))


def _offset_params(th, res):
    b = res.sensor.binning
    th = np.asarray(th, float)
    dx, dy = float(th[0]) * b, float(th[1]) * b
    rot = float(th[2]) if th.size > 2 else 0.0
    sc = float(th[3]) if th.size > 3 else 0.0
    if np.hypot(dx, dy) >= 20 * b or abs(rot) > 10.0 or abs(sc) > 0.05:
        return None
    out = {"dx_px": round(dx, 4), "dy_px": round(dy, 4)}
    if rot or sc:
        out.update(rot_deg=float(f"{rot:.4g}"), scale=float(f"{sc:.4g}"))
    return out


def _offset_words(p, res) -> str:
    text = f"every source displaced by ({p['dx_px']:+.3g}, {p['dy_px']:+.3g}) px"
    rot, sc = p.get("rot_deg", 0.0), p.get("scale", 0.0)
    if not (rot or sc):
        return text + ": pointing offset"
    r = _field_radius(res)
    return (text + f", the field rotated by {rot:+.3g} deg and its scale changed by {sc:+.2g} about the sensor "
            f"centre (up to {abs(np.radians(rot)) * r:.2g} px and {abs(sc) * r:.2g} px at the farthest pixel): the "
            "pointing, position angle or plate scale differ from the WCS (its linear part)")


# drift: theta = (dx, dy [output px], accel [1], sagitta [output px]); straight first, then the path from it
#: |accel| from which a fitted path is described as dwelling at one end (the speed changes by a factor
#: ``(1 + accel) / (1 - accel)`` ~ 1.9 from one end to the other)
DRIFT_DWELL_ACCEL = 0.3
#: |sagitta| [sensor px] from which a fitted path is described as bowed (and at least 1 % of |d|)
DRIFT_BOW_PX = 0.1


def _drift_start(res, terms=(0, 1)):
    """A box of length L has variance L^2 / 12: the major axis of the linearised smear, sqrt(12) times.
    The path's terms (accel, sagitta) start at 0 (in the chained fit they start from the straight drift's)."""
    w, ang = _jitter_axes(_jitter_start(res))
    length = float(np.sqrt(12 * max(w[1], 0.05)))
    return np.array([length * np.cos(np.radians(ang)), length * np.sin(np.radians(ang)), 0.0, 0.0])


def _drift_transform(res, photo, th, spectra=None, workers=None):
    th = np.asarray(th, float)
    dx, dy = (float(v) for v in np.clip(th[:2], -400, 400))
    accel = float(np.clip(th[2], -1.0, 1.0)) if th.size > 2 else 0.0  # DriftParams' bounds: the fit sees them
    sag = float(np.clip(th[3], -200.0, 200.0)) if th.size > 3 else 0.0
    # negatives clipped as the adapter does (_store): an accelerating path's dwell end rings around undersampled
    # sources (~0.6 % of the flux below zero for accel 0.8 on a 1.5 px FWHM), which biases accel by ~25 % when
    # the fit keeps what the rendering clips
    return np.maximum(drift_smear(photo, dx, dy, accel, sag, spectra=spectra, workers=workers), 0)


def _drift_params(th, res):
    b = res.sensor.binning
    th = np.asarray(th, float)
    dx, dy = float(th[0]), float(th[1])
    accel = float(np.clip(th[2], -1.0, 1.0)) if th.size > 2 else 0.0  # what the transform applied
    sag = float(th[3]) if th.size > 3 else 0.0
    if dx < 0 or (dx == 0 and dy < 0):  # (d, accel, sagitta) and (-d, -accel, -sagitta): the same trail
        dx, dy, accel, sag = -dx, -dy, -accel, -sag
    length = float(np.hypot(dx, dy))
    if not 0 < length <= 200 or max(abs(dx), abs(dy)) * b > 1000:  # DriftParams' bounds
        return None
    if abs(sag) > 0.5 * length or abs(sag) * b > 1000:
        return None  # a bow beyond a half circle turns back on itself: an oscillation (jitter), not a drift
    return {"dx_px": round(dx * b, 4), "dy_px": round(dy * b, 4), "accel": round(accel + 0.0, 4),
            "sagitta_px": round(sag * b + 0.0, 4)}


def _drift_check(fit, res) -> str:
    """A trail is a drift only when its profile is a path's, not a smear's: a short trail is the Gaussian smear
    of its covariance (a box of length L has the variance L^2 / 12 along it; their transfer functions part at
    the fourth order, (pi f L)^4 / 180). The trail convolved with a Gaussian smear nests the jitter's Gaussian
    form with the trail's parameters (2 for the straight trail, 4 for the path) more; its gain over the smear is
    at least the drift's own gain over it, which must pass the nested test. Without a jitter fit, the round
    blur is the simpler form (the drift's parameters beyond psf_blur's one)."""
    smear = Jitter.signature.form_fit(res, "jitter", (0, 1, 2))
    if smear is not None:
        gain, k = _nested_gain(fit, smear)[0], int(fit.k)
    else:
        gain, k = _beyond_blur(fit, res)
    if k < 1 or nested_gain_significant(gain, k, NESTED_SIGMA):
        return ""
    fit.state["richer_than"] = ("jitter", "psf_blur", "psf_elongation")  # the smears its form nests
    return (f"the trail's profile is a smear's within the noise: beyond a Gaussian smear it removes {gain:.3g} chi2 "
            f"({k} parameters), no more than chance does: a blur or jitter (psf_blur, jitter), not a drift")


def _drift_words(p, res) -> str:
    dx, dy = p["dx_px"], p["dy_px"]
    accel, sag = p.get("accel", 0.0), p.get("sagitta_px", 0.0)
    length = float(np.hypot(dx, dy))
    ang = float(np.degrees(np.arctan2(dy, dx)))
    dwell = abs(accel) >= DRIFT_DWELL_ACCEL
    bowed = abs(sag) >= max(DRIFT_BOW_PX, 0.01 * length)
    if not dwell and not bowed:
        return (f"every source trailed uniformly along a {length:.3g} px segment at {ang:.0f} deg (a box profile, "
                "not a Gaussian smear): the pointing drifted during the exposure (tracking-rate error, wind push)")
    parts = []
    if dwell:
        # accel > 0: at rest at t = -1/2, the -d end; the end's direction from the trail's middle
        end = ang + (180.0 if accel > 0 else 0.0)
        end = end % 360.0 - (360.0 if end % 360.0 > 180.0 else 0.0)  # in (-180, 180]
        parts.append(f"dwelling at its {end:.0f} deg end (speed {1 + abs(accel):.2g} : {1 - abs(accel):.2g} "
                     "from end to end: an accelerating drift, as a periodic mount error makes)")
    if bowed:
        side = "counter-clockwise" if sag > 0 else "clockwise"
        parts.append(f"bowed by {abs(sag):.2g} px across its chord (turning {side}: a curved tracking path, "
                     "field rotation)")
    return (f"every source trailed along a {length:.3g} px path at {ang:.0f} deg, " + " and ".join(parts)
            + ": the pointing drifted during the exposure")


# distortion: theta = (k [sensor px^-2], p1, p2 [sensor px^-1])
def _distortion_start(res, terms=(0, 1, 2)):
    """First order: the image moved by the displacement field of unit k, p1 or p2 (``terms`` 0, 1, 2),
    ``-(dI/dx dx + dI/dy dy)``, fitted at the search sample's pixels."""
    d, b = _derivatives(res), res.sensor.binning
    ctx = search_sample(res)
    sidx = ctx["idx"]
    iy, ix = np.divmod(sidx, res.data_adu.shape[1])
    yc, xc = _sensor_centre(res)
    x, y = res.xs[ix] - xc, res.ys[iy] - yc
    fields = [(x * (x * x + y * y), y * (x * x + y * y)), decentering_shift(x, y, 1.0, 0.0),
              decentering_shift(x, y, 0.0, 1.0)]
    gx, gy = d["x"].ravel()[sidx], d["y"].ravel()[sidx]
    temps = np.stack([-(gx * fields[t][0] + gy * fields[t][1]) / b for t in terms])
    c, _ = fit_linear(res, lambda i: temps[:, np.searchsorted(sidx, i)], sidx, ctx["r"], ctx["w"])
    return np.asarray(c, float)


def _distortion_transform(res, photo, th, at=None):
    yc, xc = _sensor_centre(res)
    return radial_distortion(photo, res.ys, res.xs, yc, xc, float(th[0]), step=res.sensor.binning,
                             p1_per_px=float(th[1]), p2_per_px=float(th[2]), at=at)


def _distortion_params(th, res):
    yc, xc = _sensor_centre(res)
    rmax2 = max((res.ys - yc) ** 2) + max((res.xs - xc) ** 2)
    k, p1, p2 = (float(v) for v in th)
    # a displacement of at most 5 % of the field radius (and the parameters' bounds)
    if abs(k) * rmax2 >= 0.05 or 3 * max(abs(p1), abs(p2)) * np.sqrt(rmax2) >= 0.05 or (k == 0 and p1 == 0 and p2 == 0):
        return None
    return {"k_per_px2": k, "p1_per_px": p1, "p2_per_px": p2}


def _distortion_words(p, res) -> str:
    yc, xc = _sensor_centre(res)
    rmax = float(np.sqrt(max((res.ys - yc) ** 2) + max((res.xs - xc) ** 2)))
    radial = abs(p["k_per_px2"]) * rmax ** 3
    decent = 3 * max(abs(p["p1_per_px"]), abs(p["p2_per_px"])) * rmax ** 2
    parts = []
    if radial >= 0.25 * decent:
        parts.append(f"radially {'outward' if p['k_per_px2'] > 0 else 'inward'} by up to {radial:.2g} px, growing as "
                     "the cube of the field radius")
    if decent >= 0.25 * radial:
        parts.append(f"by a decentering (tangential) term of up to {decent:.2g} px, growing as the square of the "
                     "radius (a decentred or tilted element)")
    return "sources displaced " + " and ".join(parts) + ": distortion missing from the WCS"


#: a rigid offset leaves the sources' shape alone: a skew change of their profiles found after the shift (by the
#: nested test) may remove at most this share of the chi2 the shift removes (a one-sided coma tail of 40 % of the
#: light over 1.5 px: 0.37; true offsets, rotated or scaled fields, a decentering distortion: below 1e-3). Both a
#: lopsided PSF and a displacement varying across the field pass the nested tests of the skew and of the
#: regions' own shifts, each beyond the other too (a 3 x 3 grid of shifts does not follow a field growing as
#: r^2, and a tail moves faint and saturated sources by different amounts): this share tells which the
#: sources show (and a skew below it, with regions that do not vary, leaves the offset a candidate)
MAX_SKEW_SHARE = 0.05


def _skew_check(fit, res, idx, w, r) -> str:
    """Is the sources' shape lopsided beyond what the shift explains? The residual after the shift is fitted
    with the image's second derivatives (a symmetric change: blur, elongation) and then also its third
    derivatives (the first-order effect of a change of the PSF's third moments, ``-(1/6) k3 : grad^3 I``;
    a Taylor / Edgeworth expansion of the convolution, e.g. Kendall & Stuart vol. 1 sect. 6.17). A pointing
    offset changes the first moments only; an asymmetric PSF (coma from a tilted or decentred mirror, a
    one-sided tail) also moves each source's centroid, so the shift alone fits part of it. The offset nests in
    the offset with a skew (4 parameters more): lopsided when they pass the nested test."""
    d = _derivatives(res)
    even = [d["xx"], d["yy"], d["xy"]]
    odd = _third_derivatives(res)
    _, d_even = fit_linear(res, lambda i: np.stack([t.ravel()[i] for t in even]), idx, r, w)
    _, d_both = fit_linear(res, lambda i: np.stack([t.ravel()[i] for t in even + odd]), idx, r, w)
    gain = d_even - d_both  # chi2 the skew templates remove beyond the symmetric ones
    shift_gain = -fit.delta_m2lnl / search_sample(res)["scale"]
    if not nested_gain_significant(gain, 4, NESTED_SIGMA) or gain <= MAX_SKEW_SHARE * shift_gain:
        return ""
    return (f"the sources are lopsided, not only displaced: after the shift, a skew (third-moment) change of their "
            f"profiles removes {gain / shift_gain:.2g} as much chi2 as the shift itself: an asymmetric PSF (coma of a "
            "tilted or decentred mirror, a one-sided tail) moves the centroids as an offset would, but a rigid "
            "offset does not change the sources' shape")


def _offset_check(fit, res) -> str:
    """A pointing offset moves the whole image rigidly. After the fitted shift, the extra shift of each of
    3 x 3 regions (linearised: the model image's derivatives per region, fitted with the global levels) must
    be insignificant: the rigid offset nests in the offset with a shift of its own per region (18 parameters
    more), and a displacement that varies across the field by the nested test is a distortion, a rotation or a
    plate-scale change the WCS lacks, not a pointing offset. Nor may the sources' shape have changed
    asymmetrically (:func:`_skew_check`)."""
    if fit.delta_adu is None:
        return ""
    d = _derivatives(res)
    ctx = search_sample(res)
    idx, w = ctx["idx"], ctx["w"]
    r = ctx["r"] - frame_at(fit.delta_adu, idx)
    skew = _skew_check(fit, res, idx, w, r)
    if skew:
        return skew
    ny, nx = res.data_adu.shape
    y, x = np.divmod(idx, nx)
    cell = np.minimum(y * 3 // ny, 2) * 3 + np.minimum(x * 3 // nx, 2)
    gx, gy = d["x"].ravel()[idx], d["y"].ravel()[idx]
    info = np.bincount(cell, w * (gx * gx + gy * gy), minlength=9)
    use = info > 0.05 * info.max()
    if np.count_nonzero(use) < 4:
        return ""  # too few regions with sources to see a field dependence
    # each region's shift templates (the model's derivatives there, zero elsewhere) at the sample's pixels
    temps = np.zeros((18, idx.size))
    at = np.arange(idx.size)
    temps[2 * cell, at], temps[2 * cell + 1, at] = -gx, -gy

    def values(i):
        return temps[:, np.searchsorted(idx, i)]

    coef, dchi2 = fit_linear(res, values, idx, r, w)
    gain = -dchi2  # the chi2 the regions' own shifts remove
    if not nested_gain_significant(gain, 18, NESTED_SIGMA):
        return ""
    b = res.sensor.binning
    shifts = coef.reshape(9, 2) * b  # sensor px
    rms = float(np.sqrt(np.sum(info[use, None] * shifts[use] ** 2) / np.sum(info[use])))
    # the fitted motion at the regions' centres (weighted by their information): the common shift, and with a
    # rotation or a scale change what they add there
    yc, xc = _sensor_centre(res)
    wt = w * (gx * gx + gy * gy)
    cnt = np.maximum(np.bincount(cell, wt, minlength=9), 1e-300)
    cx = np.bincount(cell, wt * res.xs[x], minlength=9) / cnt - xc
    cy = np.bincount(cell, wt * res.ys[y], minlength=9) / cnt - yc
    p = fit.params
    rot, sc = np.radians(p.get("rot_deg", 0.0)), p.get("scale", 0.0)
    mx = p["dx_px"] + (1 + sc) * (np.cos(rot) * cx - np.sin(rot) * cy) - cx
    my = p["dy_px"] + (1 + sc) * (np.sin(rot) * cx + np.cos(rot) * cy) - cy
    motion = float(np.sqrt(np.sum(info[use] * (mx[use] ** 2 + my[use] ** 2)) / np.sum(info[use])))
    rigid = not (p.get("rot_deg", 0.0) or sc)
    return (f"the sources' displacement varies across the field beyond the fitted "
            f"{'shift' if rigid else 'shift, rotation and scale'}: the regions' own shifts differ from its "
            f"{motion:.2g} px (rms) by {rms:.2g} px rms (chi2 falls by {gain:.0f} for 18 parameters): a distortion the "
            f"WCS lacks{', or a rotation or plate-scale change' if rigid else ''}, not a pointing offset")


def _displacement_templates(res, idx, fields) -> np.ndarray:
    """First-order templates [ADU per unit] at the flat pixels ``idx`` of the model image moved by each
    displacement field (a function of the pixels' sensor coordinates (x, y) from the sensor centre returning
    (dx, dy) [sensor px])."""
    d, b = _derivatives(res), res.sensor.binning
    iy, ix = np.divmod(idx, res.data_adu.shape[1])
    yc, xc = _sensor_centre(res)
    x, y = res.xs[ix] - xc, res.ys[iy] - yc
    gx, gy = d["x"].ravel()[idx], d["y"].ravel()[idx]
    out = []
    for f in fields:
        fx, fy = f(x, y)
        out.append(-(gx * fx + gy * fy) / b)
    return np.stack(out)


def _distortion_check(fit, res) -> str:
    """A distortion is named only for what a similarity transform of the field cannot do. Over a window the
    radial term is partly a scale change and the decentering terms partly a shift and a rotation, so the two
    forms are weighed against their joint one (similarity + distortion, linearised about each form's own
    Gauss-Newton fit, on every fitted pixel: the power of the fits the judge arbitrates): the distortion is
    refused when its terms add nothing significant beyond the best similarity (NESTED_SIGMA, 3 parameters)
    while the similarity's add something beyond the distortion (4 parameters): then the field moved as a
    whole, rotated or changed scale. When neither adds to the other, the frame cannot tell them apart and
    the judge compares them on held-out pixels."""
    if fit.delta_adu is None:
        return ""
    idx, _, w = res.flat_profiled()
    r = res.flat()[1]
    sim_fit = PointingOffset.signature.fit(res, "pointing_offset")
    if sim_fit is None or sim_fit.delta_adu is None:
        return ""
    n = 1e-3  # the fields' scale (sensor px at 1000 px): the templates' sizes comparable, the fit unchanged
    sim = [lambda x, y: (np.ones_like(x), np.zeros_like(y)), lambda x, y: (np.zeros_like(x), np.ones_like(y)),
           lambda x, y: (-n * y, n * x), lambda x, y: (n * x, n * y)]
    dist = [lambda x, y: (n ** 3 * x * (x * x + y * y), n ** 3 * y * (x * x + y * y)),
            lambda x, y: decentering_shift(x, y, n * n, 0.0), lambda x, y: decentering_shift(x, y, 0.0, n * n)]

    def beyond(delta, own):
        """chi2 the joint form's templates remove beyond the form's own, about that form's fit."""
        rr = r - frame_at(delta, idx)
        _, d_own = fit_linear(res, lambda i: _displacement_templates(res, i, own), idx, rr, w)
        _, d_both = fit_linear(res, lambda i: _displacement_templates(res, i, sim + dist), idx, rr, w)
        return d_own - d_both

    over_sim = beyond(sim_fit.delta_adu, sim)
    if nested_gain_significant(over_sim, len(dist), NESTED_SIGMA):
        return ""
    over_dist = beyond(fit.delta_adu, dist)
    if not nested_gain_significant(over_dist, len(sim), NESTED_SIGMA):
        return ""
    return (f"a shift, rotation and plate-scale change of the field fit the sources' displacement better: the "
            f"distortion's terms remove only {over_sim:.3g} more chi2 beyond them (3 parameters), theirs "
            f"{over_dist:.3g} beyond the distortion's (4 parameters): a pointing, position-angle or plate-scale "
            "error (pointing_offset), not a distortion")


def _ghost_variants(res):
    if not _has_structure(res):
        return
    b = res.sensor.binning
    yc, xc = _sensor_centre(res)
    photo = res.photo_adu.astype(np.float32)
    for radius in (2.0, 5.0, 12.0, 30.0, 80.0):  # sensor px
        t = ghost_image(photo, res.ys, res.xs, yc, xc, radius / b)

        def to_params(c, radius=radius):
            return {"alpha": float(c[0]), "radius_px": radius} if 0 < c[0] < 0.1 else None

        yield Variant([t], to_params, f"radius {radius:g} px")


# --- adapters --------------------------------------------------------------------------------------------------


class BlurParams(EffectParams):
    sigma_px: float = Field(0.5, ge=0, le=50, description="std of the extra Gaussian blur [sensor pixels]",
                            json_schema_extra={"unit": "pixel"})
    halo_frac: float = Field(0.0, ge=0, lt=HALO_MAX_FRACTION,
                                 description="share of the light scattered into a wide Gaussian halo [1]",
                                 json_schema_extra={"unit": "1"})
    halo_sigma_px: float = Field(0.0, ge=0, le=200, description="std of the halo [sensor pixels]",
                                 json_schema_extra={"unit": "pixel"})


@register_effect
class PSFBlur(Effect):
    """Extra isotropic Gaussian blur of the image (defocus, seeing or optics the PSF model lacks), and/or a
    scattering halo: ``halo_frac`` of the light spread by a Gaussian of ``halo_sigma_px``, the rest in place
    (``(1 - f) I + f G_h * I``: the aureole of scattered light, Racine 1996 PASP 108 699). A core with wings (a
    Moffat or exponential broadening) is the core and the halo together."""

    name = "psf_blur"
    scaling = "frame"
    identity = {"sigma_px": 0.0, "halo_frac": 0.0}
    stages = (Stage.FIELD,)
    Params = BlurParams
    signature = TransformSignature(
        _blur_start, _blur_transform, _blur_params, [0.02, 0.002, 0.1],
        nested=[(0,), (1, 2), (0, 1, 2)], shared=((0,),),
        pattern="sources wider than the model (a Laplacian-shaped residual), or with far wings",
        explain=_blur_words)

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        p = self.params
        out = blur(data, p.sigma_px)
        if p.halo_frac:
            out = (1 - p.halo_frac) * out + p.halo_frac * blur(out, p.halo_sigma_px)
        _store(data, out)


class JitterParams(EffectParams):
    sigma_major_px: float = Field(0.5, ge=0, le=50, description="rms pointing jitter along its major axis [px]")
    sigma_minor_px: float = Field(0.2, ge=0, le=50, description="rms pointing jitter across [px]")
    angle_deg: float = Field(0.0, ge=-180, le=180, description="major axis, counter-clockwise from +x [deg]",
                             json_schema_extra={"unit": "deg", "periodic": True})
    vibration_px: float = Field(0.0, ge=0, le=50, description="amplitude of a sinusoidal vibration along angle_deg "
                                "(0: none) [px]", json_schema_extra={"unit": "pixel"})


@register_effect
class Jitter(Effect):
    """Pointing jitter during the exposure: an elongated Gaussian blur (random motion: mount vibration, wind,
    tracking), and/or a sinusoidal vibration of amplitude ``vibration_px`` along ``angle_deg`` (a resonance:
    the arcsine smear of :func:`vibration_smear`). The diagnosis fits the two forms apart (nested) and keeps
    the better."""

    name = "jitter"
    scaling = "frame"
    identity = {"sigma_major_px": 0.0, "sigma_minor_px": 0.0, "vibration_px": 0.0}
    stages = (Stage.FIELD,)
    Params = JitterParams
    signature = TransformSignature(
        _jitter_start, _jitter_transform, _jitter_params, [0.02, 0.02, 0.02, 0.02, 0.02],
        nested=[(0, 1, 2), (3, 4)], shared=((0, 1, 2),), check=_jitter_check,
        pattern="sources elongated along one direction",
        explain=_jitter_words)

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        p = self.params
        out = blur(data, p.sigma_major_px, p.sigma_minor_px, p.angle_deg)
        if p.vibration_px:
            a = np.radians(p.angle_deg)
            out = vibration_smear(out, p.vibration_px * np.cos(a), p.vibration_px * np.sin(a))
        _store(data, out)


class ElongationParams(EffectParams):
    dcxx_px2: float = Field(0.0, ge=-25, le=25, description="change of the sources' second moment along x "
                            "[sensor px^2]", json_schema_extra={"unit": "pixel^2"})
    dcyy_px2: float = Field(0.0, ge=-25, le=25, description="change of the second moment along y [sensor px^2]",
                            json_schema_extra={"unit": "pixel^2"})
    dcxy_px2: float = Field(0.0, ge=-25, le=25, description="change of the cross moment xy [sensor px^2]",
                            json_schema_extra={"unit": "pixel^2"})
    tail_px: float = Field(0.0, ge=0, le=50, description="e-folding length of a one-sided exponential tail of "
                           "the PSF (the lopsided form: coma) [sensor px]", json_schema_extra={"unit": "pixel"})
    tail_frac: float = Field(0.0, ge=0, le=1, description="share of each source's light in the tail (0: none) [1]",
                             json_schema_extra={"unit": "1"})
    tail_angle_deg: float = Field(0.0, ge=-180, le=180, description="direction of the tail, counter-clockwise from "
                                  "+x [deg]", json_schema_extra={"unit": "deg", "periodic": True})
    halo_frac: float = Field(0.0, ge=0, le=0.8, description="share of each source's light in a displaced Gaussian "
                             "halo (the flare of a fast lens off its axis; 0: none) [1]", json_schema_extra={"unit": "1"})
    halo_sigma_px: float = Field(0.0, ge=0, le=50, description="rms of the halo per axis [sensor px]",
                                 json_schema_extra={"unit": "pixel"})
    halo_dx_px: float = Field(0.0, ge=-50, le=50, description="the halo's centre from its source along the columns "
                              "[sensor px]", json_schema_extra={"unit": "pixel"})
    halo_dy_px: float = Field(0.0, ge=-50, le=50, description="the halo's centre from its source along the rows "
                              "[sensor px]", json_schema_extra={"unit": "pixel"})


@register_effect
class PSFElongation(Effect):
    """The sources' second moments differ from the model's by ``dC`` with one axis *narrower*: an
    elongated PSF (astigmatism, a tilted detector, wind shake along one axis) where the scene has a round
    one. Applied as the Gaussian filter of covariance ``dC`` (``H = exp(-2 pi^2 f^T dC f)``, the narrowing
    axis a capped deconvolution), so the second moments of every source become ``C_psf + dC`` (moments of
    a convolution add; for a Gaussian PSF the result is exact, for a Moffat its core). ``dC`` must leave
    ``C_psf + dC`` positive: a narrowing larger than the PSF's own variance has no meaning.

    Its displaced halo (``halo_frac``, set by ``newtsim init``, not fitted by the diagnosis): that share of every
    source's light in a round Gaussian of ``halo_sigma_px`` centred ``(halo_dx_px, halo_dy_px)`` from it
    (:func:`displaced_halo_transfer`: the flare of a fast lens off its axis), applied after the tail.

    Its lopsided form: ``tail_frac`` of every source's light in a one-sided exponential tail of ``tail_px``
    along ``tail_angle_deg``, the core in place (:func:`one_sided_tail`: coma, a one-sided tracking tail),
    which changes the sources' third moments, as no symmetric kernel can. The diagnosis fits the two forms
    apart (nested: the symmetric one from the linearised second moments, the lopsided one from the
    linearised first and third cumulants) and keeps the better; the applied effect is the covariance
    filter followed by the tail."""

    name = "psf_elongation"
    scaling = "frame"
    identity = {"dcxx_px2": 0.0, "dcyy_px2": 0.0, "dcxy_px2": 0.0, "tail_frac": 0.0}
    stages = (Stage.FIELD,)
    Params = ElongationParams
    signature = TransformSignature(
        _elongation_start, _elongation_transform, _elongation_params, [0.02, 0.02, 0.02, 0.02, 0.02, 0.01],
        nested=[(0, 1, 2), (3, 4, 5)], check=_elongation_check,
        pattern="sources wider than the model along one axis and narrower across (a quadrupole residual), or "
                "lopsided: a one-sided tail (a skew residual)",
        explain=_elongation_words)

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        p = self.params
        out = data
        if p.dcxx_px2 or p.dcyy_px2 or p.dcxy_px2:
            cov = np.array([[p.dcxx_px2, p.dcxy_px2], [p.dcxy_px2, p.dcyy_px2]])
            out = gaussian_filter_cov(out, cov, max_gain=ELONGATION_MAX_GAIN)
        if p.tail_frac and p.tail_px:
            out = one_sided_tail(out, p.tail_px, p.tail_frac, p.tail_angle_deg)
        if p.halo_frac:
            transfer, pad = displaced_halo_transfer(p.halo_frac, p.halo_sigma_px, p.halo_dx_px, p.halo_dy_px)
            ctype = np.complex128 if out.dtype == np.float64 else np.complex64
            out = fourier_filter(out, pad, lambda fx, fy: transfer(fx, fy).astype(ctype, copy=False))
        if out is not data:
            _store(data, out)


class OffsetParams(EffectParams):
    dx_px: float = Field(0.0, ge=-1e4, le=1e4, description="image shift along columns [sensor px]")
    dy_px: float = Field(0.0, ge=-1e4, le=1e4, description="image shift along rows [sensor px]")
    rot_deg: float = Field(0.0, ge=-10, le=10, description="rotation of the field about the sensor centre, "
                           "counter-clockwise in (x, y) [deg] (a position-angle error of the WCS)")
    scale: float = Field(0.0, ge=-0.05, le=0.05, description="plate-scale change about the sensor centre: "
                         "distances from it grow by 1 + scale [1] (a focal-length or refraction change)")


@register_effect
class PointingOffset(Effect):
    """The telescope points slightly elsewhere than the header says, about a position angle and at a plate
    scale slightly other than the header's: the whole image moves by the similarity transform of
    :func:`similarity` (shift, rotation and scale about the sensor centre; the WCS unchanged). What a
    similarity transform cannot do is a ``distortion``.

    The diagnosis fits the rigid shift first, then (chained) the similarity transform started from it; the
    form with the lower delta BIC is proposed."""

    name = "pointing_offset"
    scaling = "frame"
    identity = {"dx_px": 0.0, "dy_px": 0.0, "rot_deg": 0.0, "scale": 0.0}
    stages = (Stage.FIELD,)
    Params = OffsetParams
    signature = TransformSignature(
        _offset_start, _offset_transform, _offset_params, [0.01, 0.01, 1e-3, 1e-5], nested=[(0, 1), (0, 1, 2, 3)],
        chain=True, keep=True, pattern="dipoles on every source, all in one direction, or turning and growing across the "
                            "field as a rotation or a scale change does", check=_offset_check, explain=_offset_words)

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        p = self.params
        if not (p.rot_deg or p.scale):
            _store(data, shift(data, p.dx_px, p.dy_px))
            return
        ys, xs, yc, xc = _photo_sensor_coords(tile)
        _store(data, similarity(data, ys, xs, yc, xc, p.dx_px, p.dy_px, p.rot_deg, p.scale))


class DriftParams(EffectParams):
    dx_px: float = Field(3.0, ge=-1e3, le=1e3, description="total drift of the image along the columns during the "
                         "exposure [sensor px]", json_schema_extra={"unit": "pixel"})
    dy_px: float = Field(0.0, ge=-1e3, le=1e3, description="total drift of the image along the rows during the "
                         "exposure [sensor px]", json_schema_extra={"unit": "pixel"})
    accel: float = Field(0.0, ge=-1, le=1, description="along-track acceleration: the path's quadratic coefficient "
                         "along d over |d| (speed |d| (1 + 2 accel t), t in [-1/2, 1/2]); +1 starts at rest (the "
                         "source dwells at the -d/2 end), -1 ends at rest, 0 uniform [1]",
                         json_schema_extra={"unit": "1", "bound_reachable": True})
    sagitta_px: float = Field(0.0, ge=-1e3, le=1e3, description="bow of the trail across its chord [sensor px]; "
                              "> 0: the path turns counter-clockwise (towards d rotated by +90 deg); the path's "
                              "quadratic coefficient across is 4 sagitta", json_schema_extra={"unit": "pixel"})


@register_effect
class PointingDrift(Effect):
    """A drift of the pointing during the exposure (a tracking-rate error, a steady wind push, a periodic
    mount error, a curved tracking path): every source is trailed along the path ``p(t) = d t + (accel |d|
    d_hat + 4 sagitta n_hat) (t^2 - 1/12)``, ``t`` in [-1/2, 1/2], centred on its mid-exposure position
    (:func:`drift_path_px`, :func:`drift_smear`). ``accel = sagitta = 0``: the uniform straight drift (a box
    kernel, variance ``L^2 / 12`` along the drift).

    The diagnosis fits the straight drift (dx, dy) first, then, only when that one is a candidate, the
    whole path (dx, dy, accel, sagitta) started from it (a chained nested fit); the form with the lower
    delta BIC is proposed."""

    name = "pointing_drift"
    scaling = "frame"
    identity = {"dx_px": 0.0, "dy_px": 0.0}
    stages = (Stage.FIELD,)
    Params = DriftParams
    signature = TransformSignature(
        _drift_start, _drift_transform,
        _drift_params,
        [0.02, 0.02, 0.02, 0.02], nested=[(0, 1), (0, 1, 2, 3)], chain=True,
        pattern="sources trailed along one direction with a flat (box) profile, or along a path brighter at one "
                "end or bowed", check=_drift_check, explain=_drift_words)

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        p = self.params
        _store(data, drift_smear(data, p.dx_px, p.dy_px, p.accel, p.sagitta_px))


class DistortionParams(EffectParams):
    k_per_px2: float = Field(0.0, ge=-1e-4, le=1e-4, description="radial distortion r' = r (1 + k r^2) [px^-2]")
    p1_per_px: float = Field(0.0, ge=-1e-3, le=1e-3, description="decentering distortion, Brown (1966): dx = p1 "
                             "(r^2 + 2 x^2) + 2 p2 x y, dy = p2 (r^2 + 2 y^2) + 2 p1 x y [px^-1]")
    p2_per_px: float = Field(0.0, ge=-1e-3, le=1e-3, description="decentering distortion, second term (see "
                             "p1_per_px) [px^-1]")


@register_effect
class Distortion(Effect):
    """Field distortion about the optical axis the WCS does not describe: radial (barrel k < 0, pincushion
    k > 0) and decentering (a decentred or tilted element; Brown 1966, the Brown-Conrady model)."""

    name = "distortion"
    scaling = "signal"
    identity = {"k_per_px2": 0.0, "p1_per_px": 0.0, "p2_per_px": 0.0}
    stages = (Stage.FIELD,)
    Params = DistortionParams
    signature = TransformSignature(
        _distortion_start, _distortion_transform, _distortion_params, [1e-10, 1e-8, 1e-8], nested=[(0,), (0, 1, 2)],
        check=_distortion_check,
        pattern="source dipoles growing towards the corners (as r^3 radially, as r^2 for a decentred element)",
        explain=_distortion_words)

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        ys, xs, yc, xc = _photo_sensor_coords(tile)
        p = self.params
        _store(data, radial_distortion(data, ys, xs, yc, xc, p.k_per_px2, p1_per_px=p.p1_per_px,
                                       p2_per_px=p.p2_per_px))


# the ghost effect (its params, adapter and free-geometry signature) lives in detector/effects/ghosts.py

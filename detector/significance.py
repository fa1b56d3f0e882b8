"""The significance levels the diagnosis shares: one meaning of "significant" wherever the same test is made.

Each level is defined here once and referenced by name by the modules that test it (detector/signatures.py,
detector/morphology.py, the effect plugins, and the judge's :class:`scenes.app.compare.policy.DiagnosisPolicy`,
whose defaults take them), so that the same test cannot drift apart in two places. The audit
(examples/diagnose/threshold_audit.py) lists every other threshold of the diagnosis and its basis.
"""

from __future__ import annotations

import math

#: a single test statistic with a unit-normal null (one pixel's |z| against its noise, a fitted quantity in its
#: standard errors, a chi2 excess in its standard deviations sqrt(2 n)) is significant beyond this many sigma:
#: the "5 sigma" of a detection, a one-sided false-alarm probability of 2.9e-7 per test (a 512 x 512 frame's
#: 2.6e5 pixels then give ~0.08 false spikes)
DETECTION_SIGMA = 5.0
#: ... the same level as a one-sided false-alarm probability (2.87e-7), for tests whose null law is not normal
#: (the largest of m periodogram ordinates: m exp(-t) below it)
DETECTION_P = 0.5 * math.erfc(DETECTION_SIGMA / math.sqrt(2.0))
#: a test of a whole frame is a false alarm this rarely per frame (a frame per thousand): a search's peak over
#: every position, scale or geometry (a matched filter, a ghost's scan: the look-elsewhere correction of a
#: detection whose number of independent trials the search itself counts), or one count of the frame against its
#: expectation (the tracks of cosmic rays: a one-sided Poisson interval of this confidence's complement)
FRAME_FALSE_ALARM = 1e-3
#: a structure of the residual (the block or pixel chi2 of a whole frame, or of the pixels a candidate acts on,
#: beyond its degrees of freedom; the peak of a band-passed map) is significant beyond this many standard
#: deviations: larger than DETECTION_SIGMA because the null distribution of such a sum is fattened by the
#: model's small imperfections, which a frame of 1e5-1e7 pixels resolves (the null calibration,
#: docs/null_calibration.md, found no null frame beyond it)
STRUCTURE_SIGMA = 8.0
#: a part of something already detected as a whole belongs to it beyond this many standard deviations: a pixel of
#: a source's footprint (its core, masked or measured as the source: the model's source light over the pixel's
#: noise), a pixel of a spike's group, one source among those a ghost map predicts (a chi2 gain of its square),
#: one side of a test of a change already found significant. No look-elsewhere: the whole was detected at
#: DETECTION_SIGMA, so the part needs one-sided 0.13 %, the detection threshold of source extraction
#: (SExtractor's DETECT_THRESH is 1.5-3 sigma per pixel, Bertin & Arnouts 1996, A&AS 117, 393)
FOOTPRINT_SIGMA = 3.0
#: a change of -2 ln L between two models (a delta BIC, a Poisson deviance, a held-out sample's) by more than this
#: is "very strong" evidence (Kass & Raftery 1995, JASA 90, 773): the DESIGN contract's significance
STRONG_EVIDENCE = 10.0
#: a form that claims a residual must explain most of it: at least this share of the excess chi2 it is fitted to
#: (the judge's min_explained, min_support_share, min_catch_all_share and parameter_explained_share; a ghost
#: about its strongest copy; a line pattern through the sources): what remains looks like noise, not like the
#: rest of another effect. The same "most" of what a claim covers: the pixels a hot-pixel claim flags hot in the
#: user's dark, the excess a defective-column claim carries in long runs, the excess a periodic pattern holds in
#: one frequency, the light a source's core (the scene's PSF) holds against a halo or a tail added to it
EXPLAINS_MOST = 0.5
#: the fewest pixels on which a refit or a test of a subset of the frame (the pixels away from the saturated
#: stars, a background ring about an aperture) speaks: below it the chi2 of a few-parameter fit is far from its
#: asymptotic law and a handful of outliers decide it
MIN_TEST_PIXELS = 100
#: a population of anomalous pixels (hot or dead pixels, defective columns, pixels with random telegraph steps)
#: holds at most this fraction of a sensor's pixels: camera data sheets give 1e-5 to 1e-3 of the pixels hot or
#: dead (EMVA 1288) and a grade-2 CCD a few tens of its thousands of columns; RTS populations of CMOS sensors are
#: below a few per cent (Wang et al. 2006; Chao et al. 2019). Beyond it, a pattern of many small deviations
MAX_DEFECT_FRACTION = 0.05
#: a scale of the scene (a zero point, a sky or dark level, a PSF's width, a gain or read noise) known to a few
#: per cent: a model knows its lamp, transparency and temperature that well (the validation's measured cameras
#: differ by 1.5-3 %), so a scale 10 % off is an error of the scene, a finding. The same relative size says when a
#: smear is round: an axis ratio within it of 1 is a round blur, not an elongation
SCALE_TOLERANCE = 0.1
#: a trail is at least this many PSF FWHM long: a source's own shape (a coma or tracking tail, a misfit core) is
#: shorter, a trail (a drifting pointing, a satellite, a track of light across the frame) longer. One bar for both
#: sides of the question: a one-sided tail longer than it is refused as a PSF's (image_plane.TAIL_MAX_FWHM), a
#: straight line shorter than it is no streak (morphology.STREAK_ELONGATION)
TRAIL_MIN_FWHM = 4.0


def nested_gain_bar(extra_params: int, sigma: float = STRUCTURE_SIGMA) -> float:
    """The chi2 gain a model must make over a model it nests to be preferred: ``k + sigma sqrt(2 k)`` for its
    ``k`` extra parameters. Under the simpler model the gain (twice the log-likelihood ratio) follows a chi2
    law with k degrees of freedom, mean k and variance 2 k (Wilks 1938, Ann. Math. Stat. 9, 60); the bar is
    that law's mean plus ``sigma`` of its standard deviations (STRUCTURE_SIGMA by default: the gain is a sum
    over a frame's pixels, whose null is fattened by the model's small imperfections, as every structure)."""
    if extra_params < 1:
        raise ValueError("a nested model has at least one extra parameter")
    return extra_params + sigma * math.sqrt(2.0 * extra_params)


def nested_gain_significant(gain: float, extra_params: int, sigma: float = STRUCTURE_SIGMA) -> bool:
    """Whether a richer model's chi2 gain over the simpler model it nests (``-2 ln L`` of the simpler minus
    the richer's, on the same pixels) is significant for its ``extra_params`` extra parameters: the nested
    likelihood-ratio test of :func:`nested_gain_bar`."""
    return bool(gain >= nested_gain_bar(extra_params, sigma))


def law_verdict(value: float, error: float, own: float, other: float) -> bool | None:
    """Which of two laws a measured quantity follows (``value`` +- ``error``; ``own`` the law a candidate
    claims, ``other`` its alternative): True when it excludes ``own`` by DETECTION_SIGMA standard errors and lies
    nearer ``other``; False when it excludes ``other`` so and lies no farther from ``own``; None when it excludes
    neither (the data cannot tell them apart) or is not finite. A value far from both still excludes the one it is
    DETECTION_SIGMA errors from: the test is of the law, not of the two laws' distance."""
    if not (math.isfinite(value) and math.isfinite(error)):
        return None
    near_other = abs(value - other) < abs(value - own)
    far = abs(value - (own if near_other else other)) >= DETECTION_SIGMA * error
    return near_other if far else None

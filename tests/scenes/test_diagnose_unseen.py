"""newtsim diagnose on effects in forms it has not been told (issue 10; scenes/app/validation/unseen.py).

Catalogue effects in functional forms that neither the plugins nor ``hidden_effects.py`` use must be named
first (one of the case's accepted names, significant) and the error must fall by half after one apply; an
effect that no plugin models must get no significant plausible catalogue name, and the diagnosis's
``residual_morphology`` must describe it with the right kind (additive / multiplicative / redistributed) and
geometry; a frame with nothing hidden must give no significant candidate.

The unmarked tests run a fast subset (three catalogue forms, two effects in no plugin, one null frame:
about 1-2 min on 2 cores); the whole set (70 cases, ~25 min on 2 cores) is ``slow``. Cases that today's
diagnosis fails are ``xfail(strict=False)`` ("issue 10 in progress"): the baseline in
docs/diagnose_validation.md, section "Unseen forms and out-of-catalogue effects (issue 10)".
"""


import pytest

from scenes.app.validation import unseen

NS = vars(unseen)
CASES = NS["CASES"]

#: the fast subset: the issue's own examples (a vignetting inside a window, a quadratic straylight), a
#: catalogue effect in another law, an out-of-catalogue multiplicative local pattern and a variance gradient,
#: one null frame
FAST = ("vig_gauss_window", "sky_quadratic", "rows_telegraph", "dust_donuts", "readnoise_gradient", "null_dark")

#: cases the diagnosis still fails (run of 2026-11-25 02:04 after issue 10's fourth round, seed 11; before and
#: after in docs/diagnose_validation.md)
FAILS_TODAY: set[str] = {
    # missed (no catalogue form reaches them): a soft bleed, a one-sided coma tail (the symmetric smears cannot
    # follow it and an offset is refused: the sources are lopsided; described as light moved around the sources)
    "bloom_soft_bright", "elong_coma",
    # described right, but the empirical map halves the error only partly (light moved into rings around the
    # sources, a faint latent image, elongated glints)
    "diffraction_ring", "persistence", "satellite_glint"}

ISSUE = "issue 10 in progress"

_CACHE: dict = {}


def _row(name, tmp_path_factory):
    if name not in _CACHE:
        _CACHE[name] = NS["run_case"](name, tmp_path_factory.mktemp(name))
    return _CACHE[name]


def _check(row):
    assert row.get("first") != "error", row.get("traceback")
    group = row["group"]
    if group == "catalogue":
        # the case is detectable at all: its exact template removes more chi2 than a BIC test of one amplitude
        # needs (2 ln N ~ 25) with room for a form to be found (a case below that measures nothing)
        assert row.get("truth_chi2") is None or row["truth_chi2"] > 100, row.get("truth_chi2")
        assert row["first"] in row["accept"], (row["case"], row["ranking"])
        assert row["first_delta_bic"] < -10
        # the error falls by at least half after one apply (or was within the noise: nothing to halve)
        assert NS["error_halved"](row), (row["metric"], row["before"], row.get("after"))
    elif group == "ooc":
        # no significant, plausible catalogue name: the honest answer is a description
        assert not row["confidently_wrong"], (row["case"], row["wrong_names"])
        morph = row["residual_morphology"] or {}
        assert row["morphology_match"], (row["case"], row["kind"], row["geometry"], morph)
        # the empirical map offered by the morphology still halves the error
        assert NS["error_halved"](row), (row["metric"], row["before"], row.get("after"))
    else:
        assert row["first_any"] == "none", row["ranking"]


def _param(names):
    return [pytest.param(n, marks=pytest.mark.xfail(strict=False, reason=ISSUE)) if n in FAILS_TODAY else n
            for n in names]


def test_the_set_is_as_large_as_the_issue_asks():
    """>= 40 cases; every catalogue effect with a signature in >= 2 forms; >= 6 effects in no plugin with an
    expected kind and geometry from the vocabulary; a null frame for every base; both cameras; strong and
    weak amplitudes; full (binned) sensors and windows."""
    import detector

    with_signature = {n for n, e in detector.registry().items() if getattr(e, "signature", None)}
    cat = [c for c in CASES.values() if c.group == "catalogue"]
    ooc = [c for c in CASES.values() if c.group == "ooc"]
    assert len(cat) + len(ooc) >= 40
    # effects added after the set was built: their real-world forms are in hidden_effects.py (one each), their
    # unseen forms are still to be written (issue 10 stays open on this)
    not_yet = {"brighter_fatter", "cti", "ipc", "rts_noise", "straylight"}
    for name in with_signature - not_yet:
        assert sum(c.effect == name for c in cat) >= 2, name
    assert len(ooc) >= 6
    vocab = {"radial", "gradient", "rows", "columns", "periodic", "sources", "local", "rings", "blobs"}
    for c in ooc:
        assert c.kind in ("additive", "multiplicative", "redistributed", "mixed") and set(c.geometry) <= vocab
    assert {c.base for c in CASES.values() if c.group == "null"} == set(NS["BASES"])
    presets = {NS["BASES"][c.base]["detector"]["preset"] for c in cat}
    assert presets == {"ml11002", "imx411"}
    assert {c.strength for c in cat} == {"strong", "weak"}
    assert any(NS["BASES"][c.base]["detector"].get("binning", 1) > 1 for c in cat)


@pytest.mark.parametrize("name", _param(FAST))
def test_unseen_fast(name, tmp_path_factory):
    _check(_row(name, tmp_path_factory))


@pytest.mark.slow
@pytest.mark.parametrize("name", _param([n for n in CASES if n not in FAST]))
def test_unseen_full_set(name, tmp_path_factory):
    _check(_row(name, tmp_path_factory))


@pytest.mark.slow
@pytest.mark.xfail(strict=False, reason=ISSUE)
def test_unseen_goals(tmp_path_factory):
    """The issue's goals on the whole set: named first >= 95 %, confidently wrong 0, every out-of-catalogue case
    described, the error halved everywhere, null frames clean."""
    rows = [_row(n, tmp_path_factory) for n in CASES]
    s = NS["summary"](rows)
    assert s["named_first"]["rate"] >= 0.95, s["named_first"]
    assert s["confidently_wrong"]["n"] == 0, s["confidently_wrong"]
    assert s["morphology_match"]["n"] == s["morphology_match"]["of"], s["morphology_match"]
    assert s["error_halved"]["n"] == s["error_halved"]["of"], s["error_halved"]
    assert s["null_clean"]["n"] == s["null_clean"]["of"], s["null_clean"]

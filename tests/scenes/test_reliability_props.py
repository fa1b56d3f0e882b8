"""Property-based tests of the scene file and ``--set`` (issue 16): whatever a user writes, ``newtsim render``
exits 0 with a valid FITS file, or 2 with exactly one stderr line naming the file and the key; never a
traceback, never a partial output.

Each example is a 64 x 48 ML11002 window with a few keys changed, each to a valid or an invalid value,
written in the scene file or given with ``--set``. The command runs in this process (``scenes.app.cli.main``;
a traceback would surface as an exception, failing the test). By default a bounded number of examples runs
(seconds); ``pytest -m slow`` runs many more.
"""

from __future__ import annotations

import io
import math
import os
import shutil
import tempfile
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path

import pytest

hypothesis = pytest.importorskip("hypothesis", reason="the property-based suite needs hypothesis "
                                 "(pip install -e '.[test]')")
import tomli_w
from astropy.io import fits
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from scenes.app.cli import main
from scenes.app.outputs import STAGE_SUFFIX

BASE = {"detector": {"preset": "ml11002", "width": 64, "height": 48},
        "exposure": {"time_s": 1.0, "frame": "dark", "seed": 1}}

finite = st.floats(allow_nan=False, allow_infinity=False)
nonfinite = st.sampled_from([math.nan, math.inf, -math.inf])
text = st.text(alphabet="abcxyz019 -_", min_size=0, max_size=8)
#: an array or a table where a value is expected
structural = st.one_of(st.lists(st.integers(0, 3), min_size=1, max_size=2),
                       st.fixed_dictionaries({"a": st.integers(0, 3)}))

#: key -> (strategy of valid values, strategy of invalid values)
KEYS = {
    "exposure.time_s": (st.floats(0, 30), st.one_of(st.floats(max_value=-1e-3, allow_nan=False, allow_infinity=False),
                                                     st.floats(min_value=1.01e6, allow_infinity=False), nonfinite,
                                                     st.booleans(), finite.map(str), structural)),
    "exposure.frame": (st.sampled_from(["dark", "bias", "light"]),
                       st.one_of(st.sampled_from(["flat", "Dark", ""]), st.integers(), st.booleans())),
    "detector.width": (st.integers(8, 64), st.one_of(st.integers(max_value=0), st.booleans(),
                                                     st.integers(1, 64).map(str), st.floats(1.5, 60.5), structural)),
    "detector.height": (st.integers(8, 48), st.one_of(st.integers(max_value=0), st.booleans(), nonfinite)),
    "detector.read_noise_e": (st.floats(0, 50), st.one_of(st.floats(max_value=-1e-3, allow_nan=False,
                                                                    allow_infinity=False), nonfinite, st.booleans(),
                                                          text)),
    "pointing.ra_deg": (st.floats(0, 359.99), st.one_of(st.floats(min_value=360, allow_infinity=False),
                                                        st.floats(max_value=-1e-6, allow_infinity=False), nonfinite,
                                                        st.booleans(), finite.map(str))),
    "pointing.dec_deg": (st.floats(-90, 90), st.one_of(st.floats(min_value=90.001, allow_infinity=False),
                                                       nonfinite, st.booleans())),
    "pointing.epoch": (st.sampled_from(["2023-02-01T22:00:00", "2019-06-30T01:02:03.5", "2030-12-31T23:59:59"]),
                       st.one_of(text, st.integers(), st.booleans())),
    "sky.stars": (st.just(False), st.one_of(st.sampled_from(["yes", "no", "true", ""]), st.integers(0, 2))),
    "sky.background_mag_arcsec2": (st.floats(15, 25), st.one_of(st.floats(max_value=4.99, allow_infinity=False),
                                                                nonfinite, st.booleans(), finite.map(str))),
    "psf.fwhm_arcsec": (st.floats(0.5, 20), st.one_of(st.floats(max_value=0, allow_infinity=False), nonfinite,
                                                      st.booleans(), structural)),
    "exposure.seed": (st.integers(0, 2 ** 63 - 1), st.one_of(st.integers(max_value=-1), st.booleans(),
                                                             st.floats(0.5, 1e6), st.integers(0, 99).map(str))),
    "exposure.bogus_key": (st.nothing(), st.integers()),
}


def _assign(table: dict, key: str, value) -> None:
    node = table
    *parents, last = key.split(".")
    for p in parents:
        node = node.setdefault(p, {})
    node[last] = value


def _toml_literal(value) -> str:
    """``value`` as the text of ``--set KEY=TEXT`` (TOML: strings quoted, nan/inf as TOML writes them)."""
    if isinstance(value, float) and math.isnan(value):
        return "nan"
    if isinstance(value, float) and math.isinf(value):
        return "inf" if value > 0 else "-inf"
    if isinstance(value, list):
        return "[" + ", ".join(_toml_literal(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{k} = {_toml_literal(v)}" for k, v in value.items()) + " }"
    return tomli_w.dumps({"v": value}).partition(" = ")[2].strip()


@st.composite
def cases(draw):
    """(changes [(key, value, valid)], how each is given: 'file' or 'set'); at most one invalid change."""
    keys = draw(st.lists(st.sampled_from(sorted(KEYS)), min_size=1, max_size=4, unique=True))
    bad = None if "exposure.bogus_key" in keys else draw(st.one_of(st.none(), st.sampled_from(keys)))
    changes = []
    for k in keys:
        valid, invalid = KEYS[k]
        if k == bad or k == "exposure.bogus_key":
            changes.append((k, draw(invalid), False))
        else:
            changes.append((k, draw(valid), True))
    how = [draw(st.sampled_from(["file", "set"])) for _ in changes]
    return changes, how


def _run(args) -> tuple[int, str]:
    out, err = io.StringIO(), io.StringIO()
    with redirect_stdout(out), redirect_stderr(err):
        try:
            main([str(a) for a in args])
            code = 0
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 1
    return code, err.getvalue()


def check_case(case) -> None:
    changes, how = case
    d = Path(tempfile.mkdtemp(prefix="nts-prop-"))
    try:
        scene = {k: dict(v) for k, v in BASE.items()}
        sets = []
        for (key, value, _), where in zip(changes, how):
            if where == "file":
                _assign(scene, key, value)
            else:
                sets += ["--set", f"{key}={_toml_literal(value)}"]
        # tomli_w writes nan/inf as TOML's nan/inf: the file then holds exactly what the user typed
        path = d / "scene.toml"
        path.write_text(tomli_w.dumps(scene))
        out = d / "frame.fits"
        code, err = _run(["render", path, "-o", out, "--no-png", *sets])
        invalid = [k for k, _, ok in changes if not ok]
        lines = err.strip().splitlines()
        assert "Traceback" not in err
        if not invalid:
            assert code == 0, (case, err)
            with fits.open(out) as hdul:
                h = hdul[0].header
                assert hdul[0].data.shape == (h["NAXIS2"], h["NAXIS1"])
                assert "SCENE" in hdul and "TRUTH" in hdul
        else:
            assert code == 2, (case, err)
            assert len(lines) == 1, (case, err)
            assert lines[0].startswith("newtsim: error: ") and "scene.toml" in lines[0], (case, err)
            assert f"'{invalid[0]}'" in lines[0], (case, err)
            assert not out.exists()
        assert not [p for p in os.listdir(d) if p.endswith(STAGE_SUFFIX) or ".part" in p], os.listdir(d)
    finally:
        shutil.rmtree(d, ignore_errors=True)


COMMON = {"deadline": None, "derandomize": True,
          "suppress_health_check": [HealthCheck.too_slow, HealthCheck.filter_too_much]}


@settings(max_examples=40, **COMMON)
@given(cases())
def test_scene_and_set_values_render_or_fail_in_one_line(case):
    check_case(case)


@pytest.mark.slow
@settings(max_examples=600, **{**COMMON, "derandomize": False})
@given(cases())
def test_scene_and_set_values_render_or_fail_in_one_line_many(case):
    check_case(case)

"""The thesis's tables beside newtsim's (examples/scenarios/thesis_tables.toml and run_table.py --thesis).

Independent reference: the thesis text itself (../shared/reference/thesis.txt): every number of the data file
must appear in it; and the comparison column is the file's value next to a frame newtsim renders.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "examples" / "scenarios"))
import run_table

THESIS = ROOT / ".." / "shared" / "reference" / "thesis.txt"


def test_thesis_values_file_parses_and_covers_the_tables():
    rows = run_table.load_thesis()
    tables = {t for r in rows for t in r["tables"]}
    assert tables == set(run_table.THESIS_TABLES)  # every table of the issue has a row
    for r in rows:
        assert (run_table.HERE / f"{r['scenario']}.toml").is_file()
        assert set(r["values"]) <= set(run_table.QUANTITIES)


def test_thesis_values_are_the_thesis_numbers():
    if not THESIS.is_file():
        pytest.skip(f"thesis text not found: {THESIS}")
    text = THESIS.read_text()
    nums = set(re.findall(r"\d+(?:\.\d+)?", text))
    for r in run_table.load_thesis():
        for part in ("values", "real"):
            for k, v in r.get(part, {}).items():
                if isinstance(v, str):
                    continue
                s = f"{v:g}" if float(v) != int(v) else str(int(v))
                assert s in nums or f"{v:.2f}" in nums, (r["label"], k, v)


def test_bad_rows_are_refused(tmp_path):
    bad = tmp_path / "t.toml"
    bad.write_text('[[row]]\ntables = [99]\nlabel = "x"\nscenario = "s01_bias_imx411"\nvalues = { std = 1.0 }\n')
    with pytest.raises(ValueError, match="tables"):
        run_table.load_thesis(bad)
    bad.write_text('[[row]]\ntables = [10]\nlabel = "x"\nscenario = "s01_bias_imx411"\nvalues = { sigma = 1.0 }\n')
    with pytest.raises(ValueError, match="sigma"):
        run_table.load_thesis(bad)


def test_comparison_column_on_a_small_window(tmp_path):
    rows = [r for r in run_table.load_thesis() if r["tables"] == [10]]
    comps = [run_table.compare_row(r, None, ["detector.width=256", "detector.height=256"]) for r in rows]
    q = {(c["label"], x["quantity"]): x for c in comps for x in c["quantities"]}
    unb = q[("Scenario 1, bias, unbinned", "median")]
    assert unb["thesis"] == 1002 and unb["newtsim"] == pytest.approx(1000, abs=1)  # bias 1000 ADU set from Annex VII
    assert unb["rel_diff"] == pytest.approx(unb["newtsim"] / 1002 - 1)
    md = run_table.thesis_markdown(comps)
    assert "| 10 | Scenario 1, bias, 4x4 binned" in md and "newtsim/thesis - 1" in md
    # a window's counts are scaled to the full sensor by area
    assert comps[0]["window_area_ratio"] == pytest.approx(14192 * 10640 / 256 ** 2)

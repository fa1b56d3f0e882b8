"""The benchmark record's contract (benchmarks/run.py): ratios are read from every benchmark's JSON, the quick
check fails on a ratio worse than the stored one by more than the margin and passes within it, and the planted
slowdown (NEWTSIM_BENCH_SLOW, benchmarks/stages.py) really doubles the work of the stage it names."""

import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import run as bench  # benchmarks/run.py
import stages  # benchmarks/stages.py


def test_every_benchmark_in_the_folder_is_run_by_make_bench():
    scripts = {p.name for p in (ROOT / "benchmarks").glob("bench_*.py")}
    assert scripts == {b[0] for b in bench.BENCHES.values()}


def test_the_check_fails_beyond_the_margin_and_passes_within_it():
    c = bench.CHECKED
    stored = {"detector_fullframe": {c: 2.0, "chain_wall_over_plain_numpy": 1.0}}

    def quick(cpu, wall):
        return {"detector_fullframe": {"ratios": {c: cpu, "chain_wall_over_plain_numpy": wall}}}

    assert bench.check(quick(2.0 * (1 + bench.MARGIN) * 0.99, 1.0), stored, bench.MARGIN) == []
    assert bench.check(quick(1.2, 1.0), stored, bench.MARGIN) == []  # faster is never a failure
    bad = bench.check(quick(2.0 * (1 + bench.MARGIN) * 1.01, 1.0), stored, bench.MARGIN)
    assert len(bad) == 1 and c in bad[0]
    # the wall-clock ratios are recorded, not checked (a shared machine scatters them by tens of per cent)
    assert bench.check(quick(2.0, 3.0), stored, bench.MARGIN) == []
    assert bench.check({"detector_fullframe": {"error": "job failed"}}, stored, bench.MARGIN)


def test_the_stored_history_holds_quick_figures_for_the_check():
    lines = [json.loads(x) for x in (ROOT / "benchmarks" / "history" / "history.jsonl").read_text().splitlines() if x]
    assert lines and all({"date", "commit", "machine"} <= set(rec) for rec in lines)
    stored = bench.stored_quick()
    assert stored["detector_fullframe"][bench.CHECKED] > 0


def test_the_ratios_of_a_benchmark_json():
    j = {"reference_plain_numpy": {"inner_s": 2.0, "inner_cpu_s": 2.0, "peak_rss_gib": 0.4},
         "newtsim_all_effects": {"inner_s": 3.0, "inner_cpu_s": 5.0, "peak_rss_gib": 0.6}}
    ratios, mem, _ = bench.x_detector(j)
    assert ratios == {"chain_wall_over_plain_numpy": 1.5, "chain_cpu_over_plain_numpy": 2.5}
    assert mem == {"newtsim": 0.6, "reference": 0.4}


def test_a_planted_slowdown_does_the_stage_twice(monkeypatch):
    """NEWTSIM_BENCH_SLOW="detector.chain:shot_noise*2": every tile draws its shot noise twice (double the
    stage's work: what the quick check must catch); the frame keeps its shape."""
    from detector import Detector, chain, make_sensor

    monkeypatch.setattr(chain, "shot_noise", chain.shot_noise)  # restored after the test
    calls = []

    def counting(fn):
        def counted(*a, **k):
            calls.append(1)
            return fn(*a, **k)
        return counted

    stages.wrap("detector.chain:shot_noise", counting)
    monkeypatch.setenv("NEWTSIM_BENCH_SLOW", "detector.chain:shot_noise*2")
    assert stages.plant() == "detector.chain:shot_noise*2"
    img = Detector(make_sensor("ml11002", {"width": 64, "height": 480})).expose(100.0, 1.0, frame_seed=1)
    assert len(calls) == 2 * 2 and img.shape == (480, 64)  # two row bands of 240 rows, each drawn twice


def test_no_plant_without_the_variable_and_an_unknown_stage_is_an_error(monkeypatch):
    monkeypatch.delenv("NEWTSIM_BENCH_SLOW", raising=False)
    assert stages.plant() is None and stages.plant("") is None
    with pytest.raises(AttributeError):
        stages.plant("detector.chain:no_such_stage*2")

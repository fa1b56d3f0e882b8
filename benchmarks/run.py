"""Every benchmark with its reference in the same run, as ratios; the stored history; the quick check.

Each benchmark in this folder already times newtsim against a reference doing the same work in the same run
and prints JSON. This runner starts each one in its own process, reads its JSON and keeps what does not depend
on the machine's speed: **ratios** (newtsim's time over the reference's, < 1 is faster than the reference) and
peak resident memory [GiB]. Absolute seconds are kept beside them for the record, never compared.

    python benchmarks/run.py                  # every benchmark (make bench): benchmarks/history/<date>_<commit>.json
    python benchmarks/run.py --record         # ... and one line appended to benchmarks/history/history.jsonl
    python benchmarks/run.py --quick --check  # the quick subset (make bench-quick, CI): fails on a regression
    python benchmarks/run.py --only detector_fullframe,dark_thermal

The quick check. The quick subset runs the detector chain with every effect on a 480-row band of the full-width
IMX411 and the plain-numpy reference chain on the same band, alternated 11 times in one process
(bench_detector_fullframe.py --repeat); the ratio checked is the chain's least user CPU time (all threads) over
the reference's least (:data:`CHECKED`; system time, which other jobs' I/O moves, and wall-clock ratios are
recorded, not checked). It is compared with the last
stored quick figure in history.jsonl: the check fails when ``ratio > stored x (1 + margin)`` (``--margin``,
default :data:`MARGIN` = 15 %). Why 15 %: three runs on the shared 2-core machine at a load average of ~20 gave
total-CPU ratios of 2.440, 2.446 and 2.462 (0.9 % apart; the wall ratios of the same runs 1.68-2.02), a fourth
1.891 through the reference's system time (hence user time), while the charge stage done twice
(``NEWTSIM_BENCH_SLOW="detector.chain:Detector.charge_tile*2"``, a 2x slower stage, benchmarks/stages.py
:func:`plant`) gave 3.08 (+26 %); docs/performance.md has the runs. The variable plants the slowdown in the
benchmark's newtsim process, so the check can be seen to fail with it and pass without it
(tests/test_bench_check.py checks the plant itself). A ratio over the margin is measured once more and the check
fails only when the second measurement is over it too.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
HISTORY = HERE / "history"
HISTORY_FILE = HISTORY / "history.jsonl"
GIB = 1024.0

#: relative margin of the quick check: a ratio may be this much worse than the stored one before it fails
MARGIN = 0.15
#: the ratio the quick check compares: the detector chain's least user CPU time (all threads, the timed part)
#: over the alternated turns, over the plain-numpy reference's least; the system time (writing the FITS file,
#: first touching memory) is what other jobs on the machine move most; the other ratios are recorded beside it
CHECKED = "chain_user_cpu_over_plain_numpy"


def _g(d: dict, *keys, default=None):
    for k in keys:
        if not isinstance(d, dict) or k not in d:
            return default
        d = d[k]
    return d


def _ratio(a, b):
    return round(a / b, 4) if a is not None and b else None


# --- what each benchmark's JSON gives: {ratio name: newtsim / reference}, peak memory [GiB], seconds -----------

def x_detector(j):
    n, r = j["newtsim_all_effects"], j["reference_plain_numpy"]
    ratios = {"chain_wall_over_plain_numpy": _ratio(n["inner_s"], r["inner_s"]),
              "chain_cpu_over_plain_numpy": _ratio(n["inner_cpu_s"], r["inner_cpu_s"])}
    if "inner_user_s" in n:  # the alternated turns (--repeat): user CPU time apart
        ratios["chain_user_cpu_over_plain_numpy"] = _ratio(n["inner_user_s"], r["inner_user_s"])
    return ratios, \
        {"newtsim": n["peak_rss_gib"], "reference": r["peak_rss_gib"]}, \
        {"newtsim": n["inner_s"], "reference": r["inner_s"], "newtsim_cpu": n["inner_cpu_s"], "reference_cpu": r["inner_cpu_s"]}


def x_navstar(j):
    n, r = j["newtsim_navstar71"], j["reference_plain_numpy"]
    return {"scene_wall_over_plain_numpy": _ratio(n["inner_s"], r["inner_s"]),
            "scene_cpu_over_plain_numpy": _ratio(n["inner_cpu_s"], r["inner_cpu_s"])}, \
        {"newtsim": n["peak_rss_gib"], "reference": r["peak_rss_gib"]}, {"newtsim": n["inner_s"], "reference": r["inner_s"]}


def x_sensor(j):
    i, c = j["imx411"], j["ml11002_cti"]
    return {"imx411_new_effects_over_without": i["time_ratio"], "imx411_new_effects_cpu_over_without": i["cpu_ratio"],
            "ml11002_cti_over_without": _ratio(c["with_cti"]["inner_s"], c["without_cti"]["inner_s"])}, \
        {"newtsim": i["with_bf_ipc_rts_persistence"]["peak_rss_gib"], "reference": i["without_new_effects"]["peak_rss_gib"]}, \
        {"newtsim": i["with_bf_ipc_rts_persistence"]["inner_s"], "reference": i["without_new_effects"]["inner_s"]}


def x_trace(j):
    # newtsim_vignetting_<design> against batoid_<design>: the same rays, so a time ratio is 1 / speed ratio
    news = {k: v for k, v in j.items() if k.startswith("newtsim_vignetting_")}
    r, mem, sec = {}, {}, {}
    for k, v in news.items():
        b = j.get("batoid_" + k.removeprefix("newtsim_vignetting_"), {})
        r[f"{k}_over_batoid"] = _ratio(v.get("seconds"), b.get("seconds"))
        r[f"{k}_cpu_over_batoid"] = _ratio(v.get("cpu_s"), b.get("cpu_s"))
        bp = j.get("batoid_paraboloid_" + k.removeprefix("newtsim_vignetting_"))
        if bp:
            r[f"{k}_over_batoid_paraboloid"] = _ratio(v.get("seconds"), bp.get("seconds"))
            r[f"{k}_cpu_over_batoid_paraboloid"] = _ratio(v.get("cpu_s"), bp.get("cpu_s"))
        mem[k] = v.get("peak_rss_gib")
        sec[k], sec["batoid_" + k.removeprefix("newtsim_vignetting_")] = v.get("seconds"), b.get("seconds")
    return r, mem, sec


def x_gradients(j):
    p = j["plain_forward"]["median_s"]
    return {"ad_gradient_over_plain_forward": _ratio(j["ad_gradient"]["median_s"], p),
            "finite_differences_over_plain_forward": _ratio(j["finite_difference_jacobian_s"], p)}, {}, \
        {"ad_gradient": j["ad_gradient"]["median_s"], "plain_forward": p}


def x_alignment(j):
    r = j["reference_plain_moments_64_nodes_s"]
    return {"joint_fit_over_plain_moments": _ratio(j["joint_fit_s"], r),
            "rank_families_over_plain_moments": _ratio(j["rank_families_s"], r)}, {}, \
        {"joint_fit": j["joint_fit_s"], "rank_families": j["rank_families_s"], "reference": r}


def x_characterize(j):
    c, r = j["characterize"], j.get("reference_read_float32_mean_std", {})
    return {"characterize_over_read_mean_std": _ratio(c["wall_s"], r.get("wall_s"))}, \
        {"newtsim": c["peak_rss_gib"], "reference": r.get("peak_rss_gib")}, {"newtsim": c["wall_s"], "reference": r.get("wall_s")}


def x_compare(j):
    return {"compare_over_render": round(j["compare_over_render"], 4),
            "diagnose_over_render": round(j["diagnose_over_render"], 4) if "diagnose_over_render" in j else None}, \
        {"compare": round(j["compare_peak_rss_mb"] / GIB, 3), "diagnose": round(j.get("diagnose_peak_rss_mb", 0) / GIB, 3),
         "reference": round(j["render_peak_rss_mb"] / GIB, 3)}, \
        {"compare": j["compare_s"], "diagnose": j.get("diagnose_s"), "reference": j["render_s"]}


def x_dark(j):
    r, s = {}, {}
    for k, v in j.items():
        r[f"{k}_both_forms_over_linear_ramp"] = _ratio(v["dark_gradient_both_forms_s"], v["reference_linear_ramp_only_s"])
        s[k] = v["dark_gradient_both_forms_s"]
    return r, {}, s


def x_diagnose(j):
    return {"diagnose_over_render": j["ratio_to_render"]}, \
        {"newtsim": round(j["peak_rss_mb"] / GIB, 3), "reference": round(j["render_peak_rss_mb"] / GIB, 3)}, \
        {"newtsim": j["diagnose_s"], "reference": j["reference"]["render_s"]}


def x_drift(j):
    return {"drift_over_straight_fit": _ratio(j["drift_s"], j["reference"]["straight_s"]),
            "drift_over_jitter_fit": _ratio(j["drift_s"], j["reference"]["jitter_s"])}, {}, \
        {"newtsim": j["drift_s"], "reference": j["reference"]["straight_s"]}


def x_misalignment(j):
    return {"candidates_over_render": j["ratio_to_render"]}, {}, \
        {"newtsim": j["misalignment_s"], "reference": j["reference"]["render_s"]}


def x_series(j):
    return {"series_over_single_diagnose": j["ratio_to_single"]}, {"newtsim": round(j["peak_rss_mb"] / GIB, 3)}, \
        {"newtsim": j["series_diagnose_s"], "reference": j["reference"]["single_diagnose_s"]}


def x_straylight(j):
    # efficiency = 1 / (variance x time): 1 / gain is newtsim's time to the plain Monte Carlo's at equal variance
    r = {f"time_at_equal_variance_over_plain_mc_{g['angle_deg']:g}deg": _ratio(1.0, g["gain"])
         for g in j["variance_reduction_gain"]}
    return r, {"newtsim": round(j["peak_rss_mib"] / GIB, 3)}, {"total": round(j["total_s"], 1)}


#: name: (script, full arguments, quick arguments or None, quick repeats, extractor)
def x_labels(j):
    return {"render_with_labels_over_render": j["ratio"],
            "score_over_nelder_mead_reference": _ratio(j["score_s"], j["score_reference_nelder_mead_s"])}, \
        {"newtsim": j.get("peak_rss_gib")}, {"newtsim": j["render_with_labels_s"], "reference": j["render_s"]}


def x_cti(j):
    f = j["full_frame_exposure"]
    return {"frame_with_cti_over_previous": f["cpu_ratio"],
            "cti_function_over_previous": j["cti_function"]["cpu_ratio_express1"]}, {}, \
        {"newtsim": f["well_fill_cti_cpu_s"], "reference": f["previous_cti_cpu_s"]}


def x_detection(j):
    return {"detect_time_over_photutils_alone": _ratio(j["reference_photutils_frames_per_s"],
                                                       j["detect_frames_per_s"])}, {}, \
        {"detect_frames_per_s": j["detect_frames_per_s"], "score_frames_per_s": j["score_frames_per_s"]}


BENCHES = {
    "detector_fullframe": ("bench_detector_fullframe.py", [], ["--rows", "480", "--repeat", "11"], 1, x_detector),
    "navstar71": ("bench_navstar71.py", [], None, 1, x_navstar),
    "sensor_physics": ("bench_sensor_physics.py", [], None, 1, x_sensor),
    "optics_trace": ("bench_optics_trace.py", [], None, 1, x_trace),
    "optics_gradients": ("bench_optics_gradients.py", [], None, 1, x_gradients),
    "alignment": ("bench_alignment.py", [], None, 1, x_alignment),
    "dark_thermal": ("bench_dark_thermal.py", [], None, 1, x_dark),
    "drift_path": ("bench_drift_path.py", [], None, 1, x_drift),
    "diagnose": ("bench_diagnose.py", [], None, 1, x_diagnose),
    "misalignment": ("bench_misalignment.py", [], None, 1, x_misalignment),
    "series": ("bench_series.py", [], None, 1, x_series),
    "compare_fullframe": ("bench_compare_fullframe.py", [], None, 1, x_compare),
    "characterize": ("bench_characterize.py", [], None, 1, x_characterize),
    "straylight": ("bench_straylight.py", ["--plot", "{tmp}/pst.png"], None, 1, x_straylight),
    "labels": ("bench_labels.py", [], None, 1, x_labels),
    "cti": ("bench_cti.py", [], None, 1, x_cti),
    "detection": ("bench_detection.py", [], None, 1, x_detection),
}


def run_one(name: str, quick: bool, tmp: str) -> dict:
    script, full, fast, repeats, extract = BENCHES[name]
    args = [a.replace("{tmp}", tmp) for a in (fast if quick else full)]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT)] + [p for p in [os.environ.get("PYTHONPATH")] if p])}
    runs = []
    for _ in range(repeats if quick else 1):
        p = subprocess.run([sys.executable, str(HERE / script), *args], cwd=ROOT, env=env, capture_output=True,
                           text=True, check=False)
        text = p.stdout[p.stdout.find("{"):] if "{" in p.stdout else ""
        try:
            runs.append(extract(json.loads(text)))
        except (ValueError, KeyError, TypeError) as e:
            return {"error": f"{script} exited {p.returncode}: {type(e).__name__} {e}; {p.stderr.strip()[-800:]}"}
    ratios = {k: statistics.median([r[0][k] for r in runs if r[0].get(k) is not None] or [None])
              if any(r[0].get(k) is not None for r in runs) else None for k in runs[0][0]}
    out = {"ratios": ratios, "peak_rss_gib": runs[-1][1], "seconds": runs[-1][2], "args": args}
    if len(runs) > 1:
        out["ratio_runs"] = {k: [r[0][k] for r in runs] for k in runs[0][0]}
    return out


def git(*args) -> str:
    try:
        return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def machine() -> dict:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"node": platform.node(), "cpu": cpu, "cpus": os.cpu_count(), "python": platform.python_version(),
            "load_avg_1min": round(os.getloadavg()[0], 2)}


def stored_quick(history: Path = HISTORY_FILE) -> dict:
    """The last stored quick figures: {benchmark: {ratio name: value}}."""
    last = {}
    if history.is_file():
        for line in history.read_text().splitlines():
            if line.strip():
                rec = json.loads(line)
                if rec.get("quick"):
                    last = rec["quick"]
    return {k: v.get("ratios", {}) for k, v in last.items()}


def check(quick: dict, stored: dict, margin: float) -> list[str]:
    """Regressions: every ratio worse than the stored one by more than ``margin`` (relative)."""
    bad = []
    for bench, res in quick.items():
        if "error" in res:
            bad.append(f"{bench}: {res['error']}")
            continue
        for k, v in res["ratios"].items():
            if k != CHECKED:  # recorded, not checked: see the module docstring
                continue
            ref = stored.get(bench, {}).get(k)
            if v is not None and ref and v > ref * (1 + margin):
                bad.append(f"{bench}.{k}: {v:.3f} > stored {ref:.3f} x {1 + margin:.2f} = {ref * (1 + margin):.3f}")
    return bad


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="only the quick subset (CI)")
    ap.add_argument("--check", action="store_true", help="with --quick: fail on a ratio worse than the stored one")
    ap.add_argument("--margin", type=float, default=MARGIN, help=f"relative margin of --check (default {MARGIN})")
    ap.add_argument("--record", action="store_true", help="append this run to benchmarks/history/history.jsonl")
    ap.add_argument("--only", default=None, help="comma-separated benchmark names")
    ap.add_argument("--no-quick", action="store_true", help="a full run without the quick subset's figures")
    ap.add_argument("--skip", default="", help="comma-separated benchmark names to leave out")
    ap.add_argument("--history", default=str(HISTORY_FILE), help=argparse.SUPPRESS)
    ap.add_argument("--out", default=None, help="the run's JSON (default benchmarks/history/<date>_<commit>.json)")
    a = ap.parse_args(argv)
    names = a.only.split(",") if a.only else [n for n, b in BENCHES.items() if b[2] is not None or not a.quick]
    names = [n for n in names if n not in a.skip.split(",")]
    unknown = [n for n in names if n not in BENCHES]
    if unknown:
        print(f"benchmarks/run.py: unknown benchmark {unknown[0]!r}; expected one of {', '.join(BENCHES)}",
              file=sys.stderr)
        return 2
    now = dt.datetime.now(dt.timezone.utc)
    rec = {"date": now.isoformat(timespec="seconds"), "commit": git("rev-parse", "--short=12", "HEAD"),
           "dirty": bool(git("status", "--porcelain", "--untracked-files=no")), "machine": machine(),
           "planted_slowdown": os.environ.get("NEWTSIM_BENCH_SLOW") or None}
    results: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        for n in names:
            if a.quick and BENCHES[n][2] is None:
                continue
            print(f"[bench] {n}{' (quick)' if a.quick else ''} ...", file=sys.stderr, flush=True)
            results[n] = run_one(n, a.quick, tmp)
            print(f"[bench] {n}: {json.dumps(results[n].get('ratios', results[n]))}", file=sys.stderr, flush=True)
    rec["quick" if a.quick else "full"] = results
    if not a.quick and not a.no_quick:  # a landing's line carries the quick figures the CI check compares with
        print("[bench] quick subset ...", file=sys.stderr, flush=True)
        with tempfile.TemporaryDirectory() as tmp:
            rec["quick"] = {n: run_one(n, True, tmp) for n, b in BENCHES.items() if b[2] is not None}
    status = 0
    if a.check:
        stored = stored_quick(Path(a.history))
        if not stored:
            print(f"[bench] no stored quick figures in {a.history}: nothing to compare", file=sys.stderr)
            return 2
        bad = check(rec.get("quick", {}), stored, a.margin)
        if bad:  # a second measurement must confirm it: a loaded machine's one bad minute does not fail CI
            print(f"[bench] over the margin: {bad[0]}; measuring again to confirm", file=sys.stderr, flush=True)
            with tempfile.TemporaryDirectory() as tmp:
                again = {n: run_one(n, True, tmp) for n in rec.get("quick", {})}
            rec["quick_confirmation"] = again
            confirmed = {b.split(":")[0] for b in check(again, stored, a.margin)}
            bad = [b for b in bad if b.split(":")[0] in confirmed]
        for b in bad:
            print(f"[bench] REGRESSION {b}", file=sys.stderr)
        print(f"[bench] quick check: {'FAILED' if bad else 'passed'} (margin {a.margin:.0%} over the stored ratios)",
              file=sys.stderr)
        status = 1 if bad else 0
    text = json.dumps(rec, indent=1)
    print(text)
    if not a.quick or a.out:
        out = Path(a.out) if a.out else HISTORY / f"{now:%Y%m%dT%H%M%SZ}_{rec['commit']}.json"
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text + "\n")
        print(f"[bench] wrote {out}", file=sys.stderr)
    if a.record and status == 0:
        Path(a.history).parent.mkdir(parents=True, exist_ok=True)
        with open(a.history, "a") as f:
            f.write(json.dumps(rec, separators=(",", ":")) + "\n")
        print(f"[bench] appended to {a.history}", file=sys.stderr)
    return status


if __name__ == "__main__":
    sys.exit(main())

"""Benchmark: ``characterize`` of a full-frame IMX411 calibration set (issue 12), peak memory and wall time.

Inputs (made once with ``newtsim render``, then reused from ``--data``): 2 biases (bias_imx411.toml, seeds 1
and 2), darks at 10, 60 and 300 s (dark_imx411.toml, seeds 3-5) and 2 flats (dark_imx411.toml as a light
frame lit by ``sky.flat_e_per_s``, 1 s, seeds 6 and 7): 14192 x 10640 uint16 frames of ~300 MB each.

Measured, each in its own subprocess (``resource.getrusage(RUSAGE_CHILDREN).ru_maxrss`` of that child):

* ``characterize``: ``newtsim characterize --bias ... --dark ... --flat ... --json ... --emit-scene ...``
  (the statistics, the camera twin's maps written as FITS);
* ``reference``: the 7 frames read with astropy into float32 arrays and their plain-numpy mean and std
  (what holding the calibration set in memory costs, the old way's floor).

Goal: characterize peak <= 3 GiB. Prints JSON.

    PYTHONPATH=$PWD python benchmarks/bench_characterize.py --data /tmp/imx411_cal [--skip-reference]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PY = sys.executable
GOAL_GIB = 3.0

FRAMES = {  # name: (scene, seed, overrides)
    "bias1": ("bias_imx411.toml", 1, []),
    "bias2": ("bias_imx411.toml", 2, []),
    "dark10": ("dark_imx411.toml", 3, ["exposure.time_s=10"]),
    "dark60": ("dark_imx411.toml", 4, ["exposure.time_s=60"]),
    "dark300": ("dark_imx411.toml", 5, ["exposure.time_s=300"]),
    "flat1": ("dark_imx411.toml", 6, ["exposure.time_s=1", "exposure.frame=light", "sky.flat_e_per_s=20000"]),
    "flat2": ("dark_imx411.toml", 7, ["exposure.time_s=1", "exposure.frame=light", "sky.flat_e_per_s=20000"]),
}

REFERENCE = """
import sys, numpy as np
from astropy.io import fits
arrs = [fits.getdata(p).astype(np.float32) for p in sys.argv[1:]]
print([float(a.mean(dtype=np.float64)) for a in arrs], [float(a.std()) for a in arrs])
"""


def make_frames(data: Path) -> dict:
    data.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    made = {}
    for name, (scene, seed, sets) in FRAMES.items():
        out = data / f"{name}.fits"
        if out.exists():
            continue
        cmd = [PY, "-m", "scenes.app.cli", "render", str(ROOT / "examples" / "scenes" / scene), "-o", str(out),
               "--seed", str(seed), "--no-png"]
        for s in sets:
            cmd += ["--set", s]
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, env=env, cwd=ROOT)
        made[name] = round(time.perf_counter() - t0, 1)
    return made


def run_child(cmd: list[str], env: dict) -> dict:
    """Wall time and peak RSS [GiB] of one child process (ru_maxrss of RUSAGE_CHILDREN, in a fresh runner)."""
    runner = ("import resource, subprocess, sys, json, time; t = time.perf_counter(); "
              "r = subprocess.run(sys.argv[1:]); w = time.perf_counter() - t; "
              "print(json.dumps({'rc': r.returncode, 'wall_s': w, "
              "'maxrss_kib': resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss}))")
    out = subprocess.run([PY, "-c", runner, *cmd], env=env, cwd=ROOT, capture_output=True, text=True)
    line = out.stdout.strip().splitlines()[-1]
    rec = json.loads(line)
    if rec["rc"] != 0:
        sys.stderr.write(out.stderr[-3000:])
    return {"rc": rec["rc"], "wall_s": round(rec["wall_s"], 1), "peak_rss_gib": round(rec["maxrss_kib"] / 2 ** 20, 3)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(Path(tempfile.gettempdir()) / "newtsim_imx411_cal"),
                    help="folder of the generated frames (made once, then reused)")
    ap.add_argument("--skip-reference", action="store_true")
    ap.add_argument("--no-scene", action="store_true", help="without --emit-scene (statistics only)")
    a = ap.parse_args(argv)
    data = Path(a.data)
    made = make_frames(data)
    f = {k: str(data / f"{k}.fits") for k in FRAMES}
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = Path(tempfile.mkdtemp(prefix="bench_char_"))
    cmd = [PY, "-m", "scenes.app.cli", "characterize", "--bias", f["bias1"], f["bias2"],
           "--dark", f["dark10"], f["dark60"], f["dark300"], "--flat", f["flat1"], f["flat2"],
           "--json", str(out / "cam.json")]
    if not a.no_scene:
        cmd += ["--emit-scene", str(out / "cam.toml")]
    res = {"frames": {"n": len(f), "shape": [10640, 14192], "dtype": "uint16", "generated_s": made,
                      "folder": str(data)},
           "characterize": run_child(cmd, env), "goal_peak_gib": GOAL_GIB}
    if not a.skip_reference:
        res["reference_read_float32_mean_std"] = run_child([PY, "-c", REFERENCE, *f.values()], env)
    c = res["characterize"]
    res["meets_goal"] = bool(c["rc"] == 0 and c["peak_rss_gib"] <= GOAL_GIB)
    if (out / "cam.json").exists():
        j = json.loads((out / "cam.json").read_text())
        res["result"] = {"read_noise_adu": j["bias"]["read_noise_adu"],
                         "dark_current_e_per_s": j["dark"]["dark_current_e_per_s"],
                         "gain_e_per_adu": j["gain"]["adopted_e_per_adu"],
                         "n_hot": j["hot_pixels"]["n_hot"], "prnu_rel": (j.get("flat") or {}).get("prnu_rel")}
    res["outputs"] = sorted(p.name for p in out.iterdir())
    print(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())

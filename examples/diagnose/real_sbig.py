"""Real data, round by round: the SBIG STL-1001E calibration set against a model of the camera.

1. The camera is characterised from its two bias frames and its darks at 10, 30, 60 and 300 s
   (``newtsim characterize``); the 150 s dark is held out.
2. **Dark**: the held-out 150 s dark is compared with that model and diagnosed; the best significant
   candidate is added (``--apply``) and the round repeated, until nothing significant is left.
3. **Flat**: a flat is compared with a scene that knows only the camera (bias and darks) and the flat's mean
   level (``[sky] flat_e_per_s``); the flat's vignetting and pixel response must come out of the
   diagnosis, round by round.

Every round writes its scene, the diagnosis JSON and the ledger (JSON + plot). Usage::

    python examples/diagnose/real_sbig.py [OUT_DIR] [--rounds N]

Reads ``../shared/realdata/sbig_stl1001e_calib`` relative to the project root (never copied).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT.parent / "shared" / "realdata" / "sbig_stl1001e_calib"


def files(pattern: str) -> list[str]:
    return sorted(str(p) for p in DATA.glob(pattern))


def camera_scene() -> dict:
    """The characterised camera as a scene (bias + darks at 10, 30, 60, 300 s; 150 s held out)."""
    from detector.characterize import characterize, emit_scene_dict

    darks = [f for f in files("darks-*.FIT") if "150s" not in f]
    result = characterize(files("bias-*.FIT"), darks)
    return emit_scene_dict(result)


def flat_scene(camera: dict, flat_path: str) -> dict:
    """The camera plus a uniform flat-field screen at the measured mean level (no vignetting, no PRNU)."""
    from detector.fits_io import read_image

    data, hdr = read_image(flat_path, role="flat")
    det = camera["detector"]
    t = float(hdr.get("EXPTIME", 23.0))
    level_adu = float(np.median(data)) - det["bias_adu"] + 0.5
    rate = level_adu * det["gain_e_per_adu"] / t - det["dark_current_e_per_s"]
    scene = {"detector": dict(det), "exposure": {"time_s": t, "frame": "light"},
             "sky": {"stars": False, "flat_e_per_s": round(rate, 3)}}
    effects = {k: v for k, v in camera.get("effects", {}).items()}
    if effects:
        scene["effects"] = effects
    return scene


def rounds(scene: dict, measured: str, out: Path, name: str, n_rounds: int) -> list[dict]:
    """compare/diagnose/apply until no candidate is significant (at most ``n_rounds``)."""
    from scenes.app.compare.run import run_rounds

    return run_rounds(scene, measured, out, name, n_rounds, log=lambda line: print(line, flush=True))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", nargs="?", default="out/realdata/sbig")
    ap.add_argument("--rounds", type=int, default=4)
    args = ap.parse_args(argv)
    if not DATA.is_dir():
        print(f"real data not found at {DATA}: nothing to do", file=sys.stderr)
        return 1
    out = Path(args.out)
    camera = camera_scene()
    dark = dict(camera, exposure={"time_s": 150.0, "frame": "dark"})
    summary = {"dark_150s": rounds(dark, files("darks-expos150s-*.FIT")[0], out, "dark150", args.rounds)}
    flat = files("flat-*.FIT")[0]
    summary["flat"] = rounds(flat_scene(camera, flat), flat, out, "flat", args.rounds)
    (out / "summary.json").write_text(json.dumps(summary, indent=1, default=float))
    print(f"wrote {out}/summary.json and the per-round scenes, JSON, ledgers and reports")
    return 0


if __name__ == "__main__":
    sys.exit(main())

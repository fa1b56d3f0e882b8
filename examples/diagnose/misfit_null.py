"""The null distribution of the validation's profiled misfit: what "within the noise" means for the outlier-count
effects' error (``scenes.app.validation.unseen.NULL_MISFIT``, the 99th percentile).

    python examples/diagnose/misfit_null.py OUT_DIR [--n 60] [--seed S]

Renders ``n`` null frames of each outlier-count base (nothing hidden, a random case's level offsets), compares
each with its model scene and writes ``OUT_DIR/misfit_null.jsonl`` (one record per frame) and
``OUT_DIR/misfit_null.json`` (percentiles overall and per base). About 1 s per frame.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np

from scenes.app.validation.random_forms import misfit_null
from scenes.app.validation.unseen import NULL_MISFIT


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--n", type=int, default=60, help="null frames per base")
    ap.add_argument("--seed", type=int, default=None, help="run seed (default: a fresh one, printed)")
    a = ap.parse_args(argv)
    seed = a.seed if a.seed is not None else int.from_bytes(os.urandom(4), "little")
    print(f"misfit_null: run seed {seed}", file=sys.stderr)

    def progress(i, n):
        print(f"\rmisfit_null: {i}/{n} frames", end="" if i < n else "\n", file=sys.stderr, flush=True)

    rows = misfit_null(a.n, seed, a.out / "work", progress=progress)
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "misfit_null.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    q = (50, 90, 95, 99)

    def pct(v):
        return {f"p{k}": float(x) for k, x in zip(q, np.percentile(v, q))} | {"max": float(np.max(v)), "n": len(v)}

    m = np.array([r["misfit"] for r in rows])
    summ = {"seed": seed, "all": pct(m), "share_above_NULL_MISFIT": float(np.mean(m >= NULL_MISFIT)),
            "per_base": {b: pct([r["misfit"] for r in rows if r["base"] == b]) for b in dict.fromkeys(r["base"] for r in rows)}}
    (a.out / "misfit_null.json").write_text(json.dumps(summ, indent=1))
    print(f"misfit of {len(m)} null frames: median {summ['all']['p50']:.3g}, 99th percentile {summ['all']['p99']:.3g} "
          f"(NULL_MISFIT = {NULL_MISFIT}: {100 * summ['share_above_NULL_MISFIT']:.1f} % above); wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The false-alarm rate of ``newtsim diagnose`` on null frames made by an independent textbook camera chain.

    python examples/diagnose/null_calibration.py OUT_DIR [--n 300] [--seed S] [--workers 2] [--title T]

Draws a fresh run seed unless ``--seed`` is given (figures are reported from seeds never used while
developing), makes ``n`` null frames and ``n / 20`` null series (:mod:`scenes.app.validation.nulls`),
diagnoses each against its own scene and writes ``OUT_DIR/nulls.jsonl`` (one record per frame or series,
written as they finish), ``OUT_DIR/summary.md`` and ``OUT_DIR/summary.json`` (false-alarm rate with its
Wilson interval, per camera and frame type, the names that fire, the null distribution of the judge's
statistics and the thresholds that hold the rate at 1 %).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from scenes.app.validation.nulls import markdown, read_jsonl, run_nulls, summarise  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--n", type=int, default=300, help="null single frames (series added: n / 20)")
    ap.add_argument("--seed", type=int, default=None, help="run seed (default: a fresh one, printed)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--title", default="")
    ap.add_argument("--summary-only", action="store_true", help="summarise OUT/nulls.jsonl again")
    a = ap.parse_args(argv)
    a.out.mkdir(parents=True, exist_ok=True)
    jl = a.out / "nulls.jsonl"
    if not a.summary_only:
        seed = a.seed if a.seed is not None else int.from_bytes(os.urandom(4), "little")
        print(f"run seed {seed}", flush=True)
        t0 = time.perf_counter()
        from scenes.app.validation.nulls import write_jsonl

        with open(jl, "w") as fh:
            def log(r):
                fh.write(json.dumps(r, default=str) + "\n")
                fh.flush()
                print(f"{r['id']} {r['class']:32s} {r['seconds']:6.1f} s  "
                      + (f"ERROR {r['error']}" if r["error"] else
                         f"{','.join(r['significant']) or '-'}{' +morph' if r['morph_significant'] else ''}"),
                      flush=True)

            recs = run_nulls(a.n, seed, a.out / "work", workers=a.workers, on_record=log)
        write_jsonl(recs, jl)  # in the matrix's order
        print(f"{len(recs)} records in {time.perf_counter() - t0:.0f} s", flush=True)
    recs = read_jsonl(jl)
    s = summarise(recs)
    (a.out / "summary.md").write_text(markdown(s, a.title))
    (a.out / "summary.json").write_text(json.dumps(s, indent=1, default=str))
    print(markdown(s, a.title))
    return 0


if __name__ == "__main__":
    sys.exit(main())

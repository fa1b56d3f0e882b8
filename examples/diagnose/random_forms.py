"""newtsim diagnose on random functional forms of its catalogue's effects, drawn from a fresh seed (issue 23).

The generator and the runner live in :mod:`scenes.app.validation.random_forms` (its docstring says what is
drawn); this script runs them::

    python examples/diagnose/random_forms.py [OUT_DIR] [-n 200] [--seed S] [--workers 2] [--families a,b]
    python examples/diagnose/random_forms.py OUT_DIR --case FAMILY-CASE_SEED    # rerun one drawn case
    python examples/diagnose/random_forms.py OUT_DIR --draw-only -n 20          # print the draws only

Without ``--seed`` the master seed is fresh (``os.urandom``), printed, and appended to ``OUT_DIR/seeds.jsonl``.
Writes ``OUT_DIR/random_forms.md`` and ``random_forms.json`` (default OUT_DIR ``random_forms_out``).
"""

from __future__ import annotations

import sys

from scenes.app.validation.random_forms import main

if __name__ == "__main__":
    sys.exit(main())

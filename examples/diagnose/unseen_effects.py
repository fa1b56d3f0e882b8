"""newtsim diagnose on effects in forms it has not been told (issue 10): the independent validation set.

The cases live in :mod:`scenes.app.validation.unseen` (its docstring says what they are); this script runs
them::

    python examples/diagnose/unseen_effects.py [OUT_DIR] [--cases a,b] [--workers N] [--seed S] [--keep]

(default OUT_DIR ``unseen_effects_out``, 2 worker processes). ``--list`` prints the cases, ``--summarise``
rebuilds the reports from ``OUT_DIR/rows``. The test ``tests/scenes/test_diagnose_unseen.py`` runs a subset.
"""

from __future__ import annotations

import sys

from scenes.app.validation.unseen import main

if __name__ == "__main__":
    sys.exit(main())

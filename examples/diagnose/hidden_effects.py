"""Prove the diagnosis on data with a hidden effect: the confusion matrix of ``newtsim diagnose``.

The cases live in :mod:`scenes.app.validation.hidden` (its docstring says what they are); this script runs
them::

    python examples/diagnose/hidden_effects.py [OUT_DIR] [--effects a,b,...] [--no-null] [--keep]

writes ``OUT_DIR/confusion.md``, ``confusion.json`` and ``confusion.png`` (default OUT_DIR:
``hidden_effects_out``). The test ``tests/scenes/test_diagnose_hidden.py`` runs the same cases.
"""

from __future__ import annotations

import sys

from scenes.app.validation.hidden import main

if __name__ == "__main__":
    sys.exit(main())

"""The diagnosis's validation sets: measured frames made with an effect the model scene lacks.

* :mod:`.hidden`: one real-world form per catalogue effect with a signature, and the null frames (the
  confusion matrix of ``newtsim diagnose``; ``examples/diagnose/hidden_effects.py`` runs it);
* :mod:`.unseen`: forms neither the plugins nor :mod:`.hidden` use, effects in no plugin, and more null
  frames (issue 10; ``examples/diagnose/unseen_effects.py`` runs it);
* :mod:`.series_cases`: frame series with an effect one frame cannot tell from another (a non-linearity on
  flats, a bias ramp against a dark-current gradient, a glow against straylight) and null series, for
  ``newtsim diagnose --series`` (``python -m scenes.app.validation.series_cases OUT`` runs them).

Each case builder makes a model scene and a measured frame, diagnoses, applies the best candidate and
compares again (docs/diagnose_validation.md). The tests (``tests/scenes/test_diagnose_hidden.py``,
``test_diagnose_unseen.py``, ``test_diagnose_series.py``) and ``benchmarks/bench_diagnose.py`` use them from
here. ``unseen`` reads ``hidden``'s namespace through :func:`runpy.run_path` (a fresh copy, whose ``BASES`` it
extends without changing the module's).
"""

"""Compare a measured frame with the scene's model, and diagnose which physical effect the model lacks.

* :mod:`.model`       the model of the frame (mean, variance, flags) and the measured frame read against it
* :mod:`.statistics`  residual statistics: chi2, regions, profiles, spectra, outliers, stars, streaks
* :mod:`.candidates`  every absent effect fitted to the residuals and ranked by delta BIC
* :mod:`.sources`     candidates of the scene's own sources (an object's light curve)
* :mod:`.apply`       ``--apply``: the scene with the best candidate and the refitted levels
* :mod:`.ledger`      the rounds' error ledger (JSON + plot)
* :mod:`.report`      the HTML report
* :mod:`.run`         the entry points below, which the CLI calls
"""

from .run import (
    SIGNIFICANT_DELTA_BIC,
    ModelFrame,
    best_candidate,
    build_model,
    diagnose_round,
    run_compare,
    run_diagnose,
    run_rounds,
)

__all__ = ["SIGNIFICANT_DELTA_BIC", "ModelFrame", "best_candidate", "build_model", "diagnose_round", "run_compare",
           "run_diagnose", "run_rounds"]

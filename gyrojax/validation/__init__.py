"""Blind validation of the gap diagnosis (docs/diagnosis.md): sealed suites of simulated
records whose hidden effects the diagnosis is not told, run through
:func:`gyrojax.diagnose.diagnose` and scored against the unsealed truth.

- :mod:`gyrojax.validation.esg`, ``.imu``, ``.platform``, ``.schuler``, ``.gyrotheodolite``: each
  rig's suite (its designs, case generator, runner and scores).
- The generic parts: the runner over any registered rig (:func:`run_cases`, :func:`score_cases`,
  :func:`separability`, :func:`oracle_detection_thresholds`) and the scoring toolbox
  (``gyrojax.validation._scoring``: :class:`Sealer`, rates with Monte Carlo standard errors,
  calibration, the Bayes oracle, the B2 refit-all baseline).

The diagnosis never imports this package (``tests/test_diagnose.py`` checks it); the benchmarks
in ``benchmarks/gap_blind*.py`` drive it and write ``benchmarks/RESULTS.md``.
"""

from ._harness import oracle_detection_thresholds as oracle_detection_thresholds
from ._harness import run_cases as run_cases
from ._harness import score_cases as score_cases
from ._harness import sealed_localisation as sealed_localisation
from ._harness import sealed_pairs as sealed_pairs
from ._harness import separability as separability
from ._scoring import Sealer as Sealer
from ._scoring import refit_all_baseline as refit_all_baseline

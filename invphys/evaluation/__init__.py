"""The evaluation protocol (docs/evaluation.md).

* :mod:`~invphys.evaluation.stats`: bootstrap intervals of means and of paired differences;
* :mod:`~invphys.evaluation.method_summary`: the per-method summary of ``report.json`` (R_actual with its
  interval, the paired difference against the nearest-neighbour baseline, cost per target);
* :mod:`~invphys.evaluation.parameters`: recovered parameters per target and method, their error in
  normalised parameter space and the parameters the data cannot pin down;
* :mod:`~invphys.evaluation.uncertainty`: does the surrogate ensemble's std rank its real errors;
* :mod:`~invphys.evaluation.baselines`: fitting and answering the spec's baselines;
* :mod:`~invphys.evaluation.plots`: R_actual per method with intervals;
* ``invphys diagnose`` (docs/diagnostics.md): :mod:`~invphys.evaluation.heldout` (rows a bundle never
  trained on, by key), :mod:`~invphys.evaluation.calibration` (coverage, TARP, SBC, quantile
  recalibration), :mod:`~invphys.evaluation.ood` (out-of-distribution scores, feature mismatch),
  :mod:`~invphys.evaluation.surrogate_errors` (error bars scaled to the surrogate's real errors),
  :mod:`~invphys.evaluation.diagnose` (the measurement) and :mod:`~invphys.evaluation.diagnose_report`
  (its files, and writing them into a bundle).
"""

"""Dataset baselines every recovery report compares against (docs/evaluation.md).

* ``nearest_neighbour``: the training row whose features are closest to the target; its parameters
  are the answer (zero model, zero simulations);
* ``npe``: an amortised posterior over the parameters given the features, trained with the ``sbi``
  library (neural posterior estimation); answers with the posterior mean, the best sample by log-prob
  or the best sample by the surrogate;
* ``local_linear``: the lookup refined by a trust-region step of a linear forward model fitted on the
  target's nearest rows (no surrogate, no simulation);
* ``corrected_search``: local candidates scored by the surrogate corrected with the nearest rows'
  real residuals (at most ``budget`` surrogate evaluations per target).

All are optimiser plugins (usable wherever an optimiser name is, e.g. ``invphys invert --method``)
that must first be fitted on training rows with :meth:`DatasetBaseline.fit`; the validate stage does so
for the spec's ``evaluation.baselines``, the invert stage for one listed under ``optimizers`` (which then
travels fitted in the run's inverter bundle). Listing them is import-cheap (sbi and torch load on use).
"""

from __future__ import annotations

from invphys.plugins.baselines._base import (
    BaselineAnswers,
    DatasetBaseline,
    answer_with_penalty,
    learns_from_rows,
)
from invphys.plugins.baselines.corrected_search import CorrectedSearch
from invphys.plugins.baselines.local_linear import LocalLinear
from invphys.plugins.baselines.nearest_neighbour import NearestNeighbour
from invphys.plugins.baselines.npe import NPEBaseline

BASELINES: list[type] = [NearestNeighbour, NPEBaseline, LocalLinear, CorrectedSearch]

__all__ = ["BASELINES", "BaselineAnswers", "CorrectedSearch", "DatasetBaseline", "LocalLinear", "NPEBaseline",
           "NearestNeighbour", "answer_with_penalty",
           "learns_from_rows"]

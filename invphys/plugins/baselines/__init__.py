"""Dataset baselines every recovery report compares against (docs/evaluation.md).

* ``nearest_neighbour``: the training row whose features are closest to the target; its parameters
  are the answer (zero model, zero simulations);
* ``npe``: an amortised posterior over the parameters given the features, trained with the ``sbi``
  library (neural posterior estimation); answers with the posterior mean, the best sample by log-prob
  or the best sample by the surrogate.

Both are optimiser plugins (usable wherever an optimiser name is, e.g. ``invphys invert --method``)
that must first be fitted on training rows with :meth:`DatasetBaseline.fit`; the validate stage does so
for the spec's ``evaluation.baselines``. Listing them is import-cheap (sbi and torch load on use).
"""

from __future__ import annotations

from invphys.plugins.baselines._base import BaselineAnswers, DatasetBaseline
from invphys.plugins.baselines.nearest_neighbour import NearestNeighbour
from invphys.plugins.baselines.npe import NPEBaseline

BASELINES: list[type] = [NearestNeighbour, NPEBaseline]

__all__ = ["BASELINES", "BaselineAnswers", "DatasetBaseline", "NPEBaseline", "NearestNeighbour"]

"""Built-in surrogates: ``mlp`` (the paper's) and ``ensemble`` (a deep ensemble with uncertainty).

Torch-free: the classes import torch inside their methods.
"""

from __future__ import annotations

from invphys.plugins.surrogates.ensemble import EnsembleSurrogate
from invphys.plugins.surrogates.mlp import MLPSurrogate

SURROGATES: list[type] = [MLPSurrogate, EnsembleSurrogate]

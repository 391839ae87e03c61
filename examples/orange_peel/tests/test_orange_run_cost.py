"""The refine's cost budget on the orange peel: runs near the parameter box's faces cost more substeps.

The paper preset's own estimate (host arithmetic, no kernels): a typical run costs 1.0 on average over the
box, runs with every parameter in the outer 10 % of its range cost about twice that, so a refine's cost
budget gives such targets fewer runs (docs/inverting.md, "A cost budget").
"""

from __future__ import annotations

import numpy as np
from invphys_orange_peel.simulator import OrangePeelSimulator

from invphys.inverter.refine import run_cost


def _edge_rows(rng: np.random.Generator, n: int, d: int) -> np.ndarray:
    u = rng.random((n, d)) * 0.1
    return np.where(rng.random((n, d)) < 0.5, u, 1.0 - u)


def test_edge_runs_cost_more_than_typical_ones_and_the_estimate_is_fixed() -> None:
    sim = OrangePeelSimulator(preset="paper", arch="cpu")
    d = sim.parameter_space().dim
    cost = run_cost(sim, 64)
    rng = np.random.default_rng(7)
    uniform, edge = rng.random((400, d)), _edge_rows(rng, 400, d)
    mean_u, mean_e = float(np.mean(cost.of(uniform))), float(np.mean(cost.of(edge)))
    assert 0.9 < mean_u < 1.1                 # fresh uniform rows: about one typical run each
    assert mean_e > 1.5 * mean_u              # the box's faces: the CFL bound asks for more substeps
    again = run_cost(OrangePeelSimulator(preset="paper", arch="cpu"), 64)
    assert np.array_equal(again.of(edge), cost.of(edge))   # from the parameters alone: no timing in it

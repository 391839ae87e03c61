"""Wire cutting of a cheese block, built on the ``invphys-anisompm`` engine (import-cheap).

Typical use::

    from invphys_cheese_cut.simulator import CheeseCutSimulator
    sim = CheeseCutSimulator(preset="tiny", arch="cpu")
    [result] = sim.simulate(sim.parameter_space().center()[None])
"""

__version__ = "0.1.0"
#: recorded with every run; bump when the physics or the scene changes results
SIMULATOR_VERSION = "0.2.0"

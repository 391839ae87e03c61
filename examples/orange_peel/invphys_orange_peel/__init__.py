"""The orange-peel AnisoMPM simulator for invphys: a scene, a parameter map and features on the ``invphys-anisompm``
engine (Taichi and Warp).

Import-cheap: nothing here imports taichi or warp. Typical use::

    from invphys_orange_peel.simulator import OrangePeelSimulator
    sim = OrangePeelSimulator(preset="tiny", arch="cpu")
    [result] = sim.simulate(sim.parameter_space().center()[None])
"""

__version__ = "0.3.0"
#: recorded with every run; bump when the physics or the scene changes results
SIMULATOR_VERSION = "0.3.0"

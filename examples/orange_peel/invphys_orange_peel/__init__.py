"""The orange-peel AnisoMPM simulator for invphys (Taichi backend; a Warp backend shares all but kernels).

Import-cheap: nothing here imports taichi or warp. Typical use::

    from invphys_orange_peel.simulator import OrangePeelSimulator
    sim = OrangePeelSimulator(preset="tiny", arch="cpu")
    [result] = sim.simulate(sim.parameter_space().center()[None])
"""

__version__ = "0.2.0"
#: recorded with every run; bump when the physics or the scene changes results
SIMULATOR_VERSION = "0.2.0"

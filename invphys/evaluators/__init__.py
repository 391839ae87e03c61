"""What searches score, beyond a plain surrogate call (not plugins: helpers that optimisers, the inverter and stages share).

* :mod:`~invphys.evaluators.uncertainty`: the shared surrogate with an uncertainty penalty
  (score = R - lambda * normalised ensemble std), for any optimiser's problem or GC-PPO's reward;
* :mod:`~invphys.evaluators.simulator_loop`: the real simulator in the loop, a population per
  batch, with a budget in simulator runs, and the ask/tell driver that refines many targets at once;
* :mod:`~invphys.evaluators.polish`: that driver from answers already simulated (only those
  below a threshold), with a log of simulated batches that a re-run replays (``active.polish``), and
  ``confirm``: re-simulate each target's best points and answer with the best mean R;
* :mod:`~invphys.evaluators.stream_refine`: per-target searches on the simulator through one open
  stream (``Simulator.simulate_feed``), generations overlapping across targets, with a per-run log.
"""

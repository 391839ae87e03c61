"""The pipeline layer: the runner and its stages (dataset, train, invert, validate, report).

It sits above :mod:`invphys.core`, :mod:`invphys.models`, :mod:`invphys.plugins` and :mod:`invphys.envs`
and orchestrates them; nothing below imports it.
"""

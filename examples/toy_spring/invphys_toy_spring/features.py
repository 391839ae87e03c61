"""Behavioural features of toy-spring runs, read from their time series."""

import numpy as np

from invphys.core.interfaces import FeatureExtractor, PluginConfig


class SpringFeatures(FeatureExtractor):
    """Peak force on the wall, time of the first zero crossing, and the share of energy damped away."""

    name = "toy_spring_features"

    class Config(PluginConfig):
        """No settings."""

    @property
    def feature_names(self):
        return ("peak_force", "first_zero_s", "energy_lost")

    def extract(self, trajectory):
        x, force, energy = (trajectory.series[n] for n in ("displacement", "force", "energy"))
        t, xv = x.times, x.values
        below = np.flatnonzero(xv <= 0.0)
        if len(below):  # interpolate the first crossing (a quarter period for light damping)
            j = below[0]
            first_zero = t[j - 1] + (t[j] - t[j - 1]) * xv[j - 1] / (xv[j - 1] - xv[j])
        else:  # never crossed within the run: censored at its end
            first_zero = t[-1]
        lost = 1.0 - energy.values[-1] / energy.values[0]
        return np.array([np.abs(force.values).max(), first_zero, lost])

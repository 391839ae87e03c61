"""Behavioural features of toy-spring runs, read from their time series."""

import numpy as np

from invphys.core.interfaces import FeatureExtractor, PluginConfig


class SpringFeatures(FeatureExtractor):
    """Peak force on the wall, time of the first zero crossing, and how much motion is left at the end."""

    name = "toy_spring_features"

    class Config(PluginConfig):
        """No settings."""

    @property
    def feature_names(self):
        return ("peak_force", "first_zero_s", "log_late_amplitude")

    def extract(self, trajectory):
        x, force = trajectory.series["displacement"], trajectory.series["force"]
        t, xv = x.times, x.values
        below = np.flatnonzero(xv <= 0.0)
        if len(below):  # interpolate the first crossing (a quarter period for light damping)
            j = below[0]
            first_zero = t[j - 1] + (t[j] - t[j - 1]) * xv[j - 1] / (xv[j - 1] - xv[j])
        else:  # never crossed within the run: censored at its end
            first_zero = t[-1]
        late = np.abs(xv[t >= 0.75 * t[-1]]).max()
        return np.array([np.abs(force.values).max(), first_zero, np.log(late / abs(xv[0]) + 1e-9)])

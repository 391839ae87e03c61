"""Core of invphys: interfaces, parameter spaces, objectives, specs, the dataset store and the runner."""

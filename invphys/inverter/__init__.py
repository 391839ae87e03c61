"""Inverter bundles: trained parts that answer any target with material parameters.

:func:`load_inverter` loads a bundle (see :mod:`invphys.inverter.writer` for its layout) into an
:class:`Inverter`; :meth:`Inverter.invert` returns an :class:`InversionResult`. Importing this package
is light (NumPy and YAML); torch is imported only where a bundle part has no NumPy form.
"""

from __future__ import annotations

from invphys.inverter.inverter import Inverter, load_inverter
from invphys.inverter.manifest import FORMAT_VERSION, BundleError
from invphys.inverter.result import Candidate, InversionResult

__all__ = ["FORMAT_VERSION", "BundleError", "Candidate", "InversionResult", "Inverter", "load_inverter"]

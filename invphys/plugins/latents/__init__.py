"""Built-in latent models: ``vae`` and ``realnvp`` (the paper's two), each with a feature head.

Torch-free: the classes import torch inside their methods.
"""

from __future__ import annotations

from invphys.plugins.latents.realnvp import RealNVPLatent
from invphys.plugins.latents.vae import VAELatent

LATENT_MODELS: list[type] = [VAELatent, RealNVPLatent]

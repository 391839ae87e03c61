"""Built-in latents plugins."""

from __future__ import annotations

LATENT_MODELS: list[type] = []

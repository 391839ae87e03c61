"""Pipeline stages run by :mod:`invphys.pipeline.runner`: one module per stage, each with ``run(ctx)`` and ``DEPENDS_ON``."""

"""Contract tests parametrised over every installed plugin (built-ins and entry points)."""

from __future__ import annotations

import pytest

from invphys import registry
from invphys.testing import ConformanceError, check_plugin_class

INFOS = registry.infos()


@pytest.mark.parametrize("info", INFOS, ids=[f"{i.kind}:{i.name}" for i in INFOS])
def test_every_plugin_meets_the_class_contract(info):
    check_plugin_class(info.cls)


def test_builtin_kinds_are_all_populated():
    kinds = {i.kind for i in INFOS if i.distribution == "invphys"}
    assert {"executor", "surrogate", "latent_model", "optimizer", "validator"} <= kinds


def test_contract_check_rejects_bad_plugins():
    from pydantic import ConfigDict

    from invphys.core.interfaces import Optimizer, PluginConfig

    class Loose(Optimizer):
        """Accepts anything."""

        name = "loose"

        class Config(PluginConfig):
            model_config = ConfigDict(extra="allow")

        def optimize(self, problem):
            raise NotImplementedError

    with pytest.raises(ConformanceError, match="extra='forbid'"):
        check_plugin_class(Loose)

    class BadName(Loose):
        """Bad name."""

        name = "Bad Name"

    with pytest.raises(ConformanceError, match="lower-case identifier"):
        check_plugin_class(BadName)

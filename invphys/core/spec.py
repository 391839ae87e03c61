"""Declarative YAML experiment specs, validated in two passes.

Pass 1 checks the *shape* (sections, types, ranges) with :class:`ExperimentSpec`. Pass 2 resolves every
plugin block (``{type: name, ...}``) through the registry and validates the rest of the block with the
plugin's own ``Config``. Every problem is reported with its path and, where known, its YAML line::

    spec.yaml: 2 problems
      optimizers.cma.sigma0 (line 14): must be > 0
      surrogate.type (line 9): No surrogate named 'mpl'. Did you mean 'mlp'? Installed surrogates: ...

A minimal spec::

    name: demo
    simulator: {type: orange_peel, preset: tiny}
    dataset: {n: 64}
    surrogate: {type: mlp}
    optimizers:
      cma: {type: cma_es, space: raw, budget: 500}
    stages: [dataset, train, invert]

The spec code lives in modules of one concept each; this module is the import path of every public name:

* :mod:`~invphys.core.spec_model`: the sections and :class:`ExperimentSpec` (pass 1, the shape);
* :mod:`~invphys.core.spec_load`: :func:`load_spec`, :func:`parse_spec`, :func:`validate_spec` (every pass);
* :mod:`~invphys.core.spec_plugins`: pass 2 (:func:`validate_plugin_blocks`) and :func:`json_schema`;
* :mod:`~invphys.core.spec_references`: pass 3 (:func:`validate_references`);
* :mod:`~invphys.core.spec_problems`: problem paths, YAML lines and the message;
* :mod:`~invphys.core.spec_output`: where a command may write (:func:`check_output_directory`);
* :mod:`~invphys.core.spec_lookup`: how the checks find plugins (the package root installs the registry).
"""

from __future__ import annotations

from invphys.core.spec_load import (
    load_spec,
    parse_spec,
    spec_problems,
    validate_spec,
    value_problems,
)
from invphys.core.spec_lookup import (
    PluginLookup,
)
from invphys.core.spec_model import (
    KEY_NEUTRAL_DEFAULTS,
    MAX_DATASET_N,
    MAX_SEED,
    MAX_TARGETS,
    OPTIMIZER_RUNNER_KEYS,
    REPORT_FORMATS,
    STAGES,
    ActiveSection,
    AdaptiveSection,
    DatasetSection,
    EvaluationMethod,
    EvaluationSection,
    ExperimentSpec,
    ExtraStore,
    Label,
    ObjectiveSection,
    PluginBlock,
    PolishSection,
    ReportFormat,
    ReportSection,
    TargetsSection,
    TrackerSection,
    optimizer_plugin_block,
)
from invphys.core.spec_output import (
    BUNDLE_MANIFEST,
    STORE_MARKERS,
    check_output_directory,
    output_problem,
)
from invphys.core.spec_plugins import (
    MODULE_CLASS_PATTERN,
    SCHEMA_DIALECT,
    SCHEMA_ID,
    json_schema,
    validate_plugin_blocks,
)
from invphys.core.spec_problems import (
    problem_line,
)
from invphys.core.spec_references import (
    validate_references,
)

__all__ = [
    "BUNDLE_MANIFEST",
    "KEY_NEUTRAL_DEFAULTS",
    "MAX_DATASET_N",
    "MAX_SEED",
    "MAX_TARGETS",
    "MODULE_CLASS_PATTERN",
    "OPTIMIZER_RUNNER_KEYS",
    "REPORT_FORMATS",
    "SCHEMA_DIALECT",
    "SCHEMA_ID",
    "STAGES",
    "STORE_MARKERS",
    "ActiveSection",
    "AdaptiveSection",
    "DatasetSection",
    "EvaluationMethod",
    "EvaluationSection",
    "ExperimentSpec",
    "ExtraStore",
    "Label",
    "ObjectiveSection",
    "PluginBlock",
    "PluginLookup",
    "PolishSection",
    "ReportFormat",
    "ReportSection",
    "TargetsSection",
    "TrackerSection",
    "check_output_directory",
    "json_schema",
    "load_spec",
    "optimizer_plugin_block",
    "output_problem",
    "parse_spec",
    "problem_line",
    "spec_problems",
    "validate_plugin_blocks",
    "validate_references",
    "validate_spec",
    "value_problems",
]

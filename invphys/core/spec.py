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
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_serializer,
    model_validator,
)

from invphys.core import safe_yaml
from invphys.core.errors import InvphysError, SpecError, did_you_mean
from invphys.core.names import check_name

STAGES: tuple[str, ...] = ("dataset", "train", "invert", "validate", "active", "report")
#: keys of an optimizer entry that the runner consumes (the rest goes to the plugin's Config)
OPTIMIZER_RUNNER_KEYS: tuple[str, ...] = ("space", "evaluator", "uncertainty_penalty")

PluginBlock = dict[str, Any]
#: a label that becomes a file or directory name (:mod:`invphys.core.names`)
Label = Annotated[str, AfterValidator(check_name)]
#: the most runs one dataset section may ask for, and the most targets
MAX_DATASET_N = 1_000_000
MAX_TARGETS = 10_000
MAX_SEED = 2**63 - 1
ReportFormat = Literal["md", "csv", "json"]
REPORT_FORMATS: tuple[ReportFormat, ...] = ("md", "csv", "json")


#: settings added after runs were cached: at these defaults they leave stage keys as they were
KEY_NEUTRAL_DEFAULTS: dict[str, dict[str, Any]] = {
    "dataset": {"extra_train": [], "early_stopping": "held_out", "adaptive": None},
    "active": {"proposals": 1, "keep_start": False, "polish": None},
}


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid")


class ExtraStore(_Section):
    """One ``dataset.extra_train`` entry: a store whose successful rows join the training split.

    Written as a plain path (every ok row of the store, however many it holds when the run starts) or as
    ``{path: ..., rows: N}``: only the store's first N ok rows, in store order (parts in the order they
    were written, rows in each part in order). Stores only append, so the first N rows of a store that
    has grown are the rows it held when it held N: a result trained on a growing store re-runs exactly,
    and its stage keys stay valid while the store grows.
    """

    path: str = Field(min_length=1, description="the store's directory (a dataset store like dataset.path)")
    rows: int | None = Field(
        None, gt=0, description="only the first `rows` ok rows in store order (default: all of them)")

    @model_validator(mode="before")
    @classmethod
    def _shorthand(cls, value: Any) -> Any:
        return {"path": value} if isinstance(value, str) else value

    @model_serializer(mode="wrap")
    def _plain_when_uncapped(self, handler: Any) -> Any:
        # a plain path dumps as one: stage keys of specs written before `rows` existed stay as they were
        return self.path if self.rows is None else handler(self)

    @classmethod
    def __get_pydantic_json_schema__(cls, core_schema: Any, handler: Any) -> dict[str, Any]:
        mapping = dict(handler.resolve_ref_schema(handler(core_schema)))
        return {"title": mapping.get("title"), "description": mapping.pop("description", None),
                "anyOf": [{"type": "string", "minLength": 1, "description": "a store's path: all its ok rows"},
                          mapping]}


class AdaptiveSection(_Section):
    """``dataset.adaptive``: generate part of the dataset where a surrogate is least sure
    (:mod:`invphys.data.adaptive`)."""

    initial: int | None = Field(None, gt=0, description="runs of the sampler's design first (default: a stored plan's when the design grows, else n // 2)")
    rounds: int = Field(4, ge=1, le=100, description="rounds the remaining runs are split into")
    surrogate: dict[str, Any] = Field(
        default_factory=lambda: {"type": "ensemble"},
        description="surrogate plugin block trained before each round; needs member uncertainty (ensemble)")
    candidates: int = Field(20, ge=1, le=1000, description="uniform candidate points scored per run chosen")
    min_gap: float = Field(0.15, ge=0, le=3, description="least distance (unit cube) between a round's points")

    @model_validator(mode="after")
    def _surrogate_named(self) -> AdaptiveSection:
        if not isinstance(self.surrogate.get("type"), str):
            raise ValueError("surrogate needs a 'type' (e.g. {type: ensemble})")
        return self


class DatasetSection(_Section):
    """Where the training data comes from: generated by the ``dataset`` stage, or an existing store."""

    n: int = Field(200, gt=0, le=MAX_DATASET_N, description="number of parameter vectors to simulate")
    sampler: Literal["uniform", "sobol", "lhs", "edge"] = Field(
        "uniform", description="sampling of [0,1]^d (edge: every coordinate in the outer 10 % of its range)")
    batch_size: int = Field(16, gt=0, le=MAX_DATASET_N, description="parameter vectors per simulator call")
    path: str | None = Field(None, description="use this existing dataset instead of generating one")
    if_missing: Literal["error", "generate"] = Field(
        "error", description="when `path` does not exist: fail, or generate `n` runs into the run directory")
    test_fraction: float = Field(0.2, gt=0, lt=1, description="held-out fraction (paper: 0.2)")
    extra_train: list[ExtraStore] = Field(
        default_factory=list, description="more stores of the same simulator whose rows join the TRAINING split "
                                          "only (held-out rows and targets stay the primary store's): each a "
                                          "path (all its ok rows) or {path, rows: N} (its first N ok rows)")
    early_stopping: Literal["held_out", "training_carve"] = Field(
        "held_out", description="rows models early-stop on: held_out (the paper's 80/20; flatters held-out "
                                "metrics a little) or training_carve (each model carves its own validation "
                                "rows from the training split; held-out metrics are unbiased)")
    seed: int | None = Field(None, ge=0, le=MAX_SEED, description="sampling seed (defaults to the spec's seed)")
    limit_minutes: float | None = Field(None, gt=0, description="stop generating after this long (resumable)")
    adaptive: AdaptiveSection | None = Field(
        None, description="generate the runs after `adaptive.initial` in rounds where a surrogate is least sure")

    @model_validator(mode="after")
    def _adaptive_fits(self) -> DatasetSection:
        if self.adaptive is not None:
            from invphys.core.adaptive import AdaptiveSettings

            try:
                AdaptiveSettings.of(self.adaptive, self.n)  # the check generation makes, at spec time
            except InvphysError as exc:
                raise ValueError(str(exc)) from None
        return self


class TargetsSection(_Section):
    """Held-out targets for inverse recovery (paper: 20 by farthest-point sampling, 10 validated)."""

    n: int = Field(20, gt=0, le=MAX_TARGETS)
    validate_n: int = Field(10, ge=0, le=MAX_TARGETS, alias="validate", description="how many to re-run through the simulator")
    selection: Literal["farthest_point", "random", "farthest_point+random"] = Field(
        "farthest_point", description="farthest_point+random: the evaluation protocol's two sets (half each)")
    values: list[dict[str, float | str]] | None = Field(
        None, min_length=1, description="your own targets, one feature mapping each (instead of held-out rows); "
                                        "an `id` names a target")
    file: str | None = Field(
        None, min_length=1, description="your own targets from a JSON, YAML or CSV file (instead of held-out rows)")

    model_config = ConfigDict(extra="forbid", populate_by_name=True)

    @field_validator("values")
    @classmethod
    def _numbers(cls, value: list[dict[str, float | str]] | None) -> list[dict[str, float | str]] | None:
        from invphys.core.user_targets import LABEL_KEYS

        for i, row in enumerate(value or []):
            for key, v in row.items():
                if isinstance(v, str) and key not in LABEL_KEYS:
                    raise ValueError(f"target {i + 1}: {key} = {v!r} is not a number")
        return value

    @model_validator(mode="after")
    def _one_source(self) -> TargetsSection:
        if self.values is not None and self.file is not None:
            raise ValueError("give your own targets as values or as a file, not both")
        return self


class ObjectiveSection(_Section):
    """A named weighted objective over features (the paper's firm and ripe peels)."""

    weights: dict[str, float] = Field(min_length=1)


class ReportSection(_Section):
    """Options of the report stage."""

    render: bool = Field(True, description="draw target and recovered runs side by side (Simulator.render) and plot their time series")
    formats: list[ReportFormat] = Field(default_factory=lambda: list(REPORT_FORMATS))


def _default_baselines() -> dict[str, PluginBlock]:
    return {"nearest_neighbour": {"type": "nearest_neighbour"}, "npe": {"type": "npe"}}


class EvaluationMethod(_Section):
    """A refinement run per validated target by the validate stage (ask/tell CMA-ES from a start)."""

    start: str = Field("nearest_neighbour", description="label (baseline or optimiser entry) whose answer starts it")
    evaluator: Literal["simulator", "surrogate"] = Field(
        "simulator", description="simulator: the real simulator in the loop (one batch per generation); "
                                 "surrogate: the shared surrogate, optionally uncertainty-penalised")
    budget: int = Field(64, ge=1, description="per target: simulator runs, or surrogate evaluations")
    popsize: int = Field(8, ge=2, description="CMA-ES population (one simulator batch over all targets)")
    sigma0: float = Field(0.1, gt=0, description="CMA-ES initial step in [0, 1]^d")
    uncertainty_penalty: float = Field(
        0.0, ge=0, description="lambda in score = R - lambda * normalised ensemble std (surrogate evaluator)")
    targets: int | None = Field(None, ge=1, description="only the first N validated targets (default all)")


class EvaluationSection(_Section):
    """The evaluation protocol (docs/evaluation.md): baselines, refinements and statistics."""

    baselines: dict[str, PluginBlock] = Field(
        default_factory=_default_baselines, description="dataset baselines answered for every target")
    methods: dict[str, EvaluationMethod] = Field(default_factory=dict)
    best_of: dict[str, list[str]] = Field(
        default_factory=dict, description="label -> answers (optimisers, baselines, methods) whose validated runs "
                                          "are compared per target; the one with the highest R_actual is kept "
                                          "(a simulator-selected answer: one run per distinct candidate)")
    reference: str = Field("nearest_neighbour", description="label the paired differences are taken against")
    bootstrap: int = Field(2000, ge=100, description="bootstrap resamples for the intervals")
    confidence: float = Field(0.95, gt=0.5, lt=1.0)
    noise_floor: bool = Field(True, description="re-simulate each validated target's true parameters")
    spread_threshold: float = Field(
        0.5, gt=0, le=1, description="flag a parameter when its spread (posterior or top answers) exceeds this "
                                     "fraction of the prior's std")


class TrackerSection(_Section):
    """Where the run's training curves, final metrics and artifacts go (docs/tracking.md).

    ``tracker: none`` is short for ``tracker: {type: none}``.
    """

    type: Literal["tensorboard", "mlflow", "none"] = Field(
        "tensorboard", description="tensorboard: event files in OUT/tensorboard; mlflow: an MLflow run; none")
    tracking_uri: str | None = Field(
        None, description="mlflow: the tracking store (default $MLFLOW_TRACKING_URI, else sqlite:///OUT/mlflow.db)")
    experiment: str | None = Field(None, description="mlflow: the experiment's name (default: the spec's name)")

    @model_validator(mode="before")
    @classmethod
    def _shorthand(cls, value: Any) -> Any:
        return {"type": value} if isinstance(value, str) else value


class PolishSection(_Section):
    """Simulator-in-the-loop polish after the last active round (``active.polish``)."""

    budget: int = Field(24, ge=1, le=100_000, description="new simulator runs per polished target (CMA-ES on "
                                                         "the simulator; the start is not re-simulated)")
    popsize: int = Field(8, ge=2, description="CMA-ES population per target (each generation of all polished "
                                              "targets is one simulator batch)")
    sigma0: float = Field(0.05, gt=0, description="CMA-ES step size in the normalised parameter cube")
    below: float = Field(0.95, gt=0, le=1, description="polish only targets whose best R_actual is below this")
    confirm: int = Field(0, ge=0, le=1000, description="after the polish, re-simulate each target's best "
                                                       "confirm_candidates points this many times and answer "
                                                       "with the best mean R (0: off)")
    confirm_candidates: int = Field(4, ge=1, le=1000, description="points per target that confirm re-simulates "
                                                                  "(a target not polished: its answer alone)")

    def key_dump(self) -> dict[str, Any]:
        """The settings as JSON; without the confirm keys when confirm is off (keys made before it existed)."""
        out = self.model_dump(mode="json")
        if not self.confirm:
            out.pop("confirm")
            out.pop("confirm_candidates")
        return out


class ActiveSection(_Section):
    """Active learning (the ``active`` stage): propose, simulate, add to the training data, retrain."""

    rounds: int = Field(3, ge=1, description="retraining rounds")
    targets: int | None = Field(None, ge=1, description="the first N targets (default: the validated ones)")
    start: str = Field("nearest_neighbour", description="label whose answers start round 0")
    budget: int = Field(540, ge=1, description="surrogate evaluations per target and round (CMA-ES)")
    popsize: int = Field(20, ge=2)
    sigma0: float = Field(0.1, gt=0)
    uncertainty_penalty: float = Field(0.0, ge=0, description="lambda of the ensemble-std penalty")
    max_epochs: int | None = Field(None, ge=1, description="cap the surrogate's epochs when retraining")
    proposals: int = Field(1, ge=1, le=64, description="proposals per target and round (independent CMA-ES "
                                                       "searches, all simulated in the round's one batch)")
    keep_start: bool = Field(False, description="the start answer's validated R_actual (validate stage) counts "
                                                "as the best so far, so the answer is never worse than its start")
    polish: PolishSection | list[PolishSection] | None = Field(
        None, description="after the last round, CMA-ES on the real simulator from each target's best answer "
                          "(label active_polished); a list: passes, each from the previous pass's answers")

    @field_validator("polish")
    @classmethod
    def _polish_passes(cls, value: Any) -> Any:
        if isinstance(value, list) and not 1 <= len(value) <= 8:
            raise ValueError(f"polish: give 1 to 8 passes, got {len(value)}")
        return value


class ExperimentSpec(_Section):
    """The whole experiment: which plugin fills each slot, with which config, and which stages run."""

    name: str = Field(min_length=1, max_length=200)
    description: str = ""
    seed: int = Field(0, ge=0, le=MAX_SEED)
    stages: list[str] | None = Field(
        None, description="stages to run, in pipeline order; default: every stage whose sections are present")
    simulator: PluginBlock
    features: PluginBlock | None = None
    executor: PluginBlock = Field(default_factory=lambda: {"type": "local"})
    dataset: DatasetSection = Field(default_factory=lambda: DatasetSection())
    surrogate: PluginBlock | None = None
    latent_models: dict[Label, PluginBlock] = Field(default_factory=dict)
    optimizers: dict[Label, PluginBlock] = Field(default_factory=dict)
    objectives: dict[Label, ObjectiveSection] = Field(default_factory=dict)
    targets: TargetsSection = Field(default_factory=lambda: TargetsSection())
    validator: PluginBlock | None = None
    evaluation: EvaluationSection = Field(default_factory=lambda: EvaluationSection())
    active: ActiveSection | None = None
    report: ReportSection = Field(default_factory=lambda: ReportSection())
    tracker: TrackerSection = Field(default_factory=lambda: TrackerSection())

    @field_validator("name")
    @classmethod
    def _printable_name(cls, value: str) -> str:
        if any(not ch.isprintable() for ch in value):
            raise ValueError("must be printable text on one line (no control characters)")
        return value

    @field_validator("stages")
    @classmethod
    def _known_stages(cls, value: list[str] | None) -> list[str] | None:
        if value is None:
            return None
        for s in value:
            if s not in STAGES:
                raise ValueError(f"unknown stage {s!r}.{did_you_mean(s, STAGES)} Stages: {', '.join(STAGES)}")
        if len(set(value)) != len(value):
            raise ValueError("a stage is listed twice")
        return sorted(value, key=STAGES.index)

    @model_validator(mode="after")
    def _stage_needs(self) -> ExperimentSpec:
        if self.stages is None:
            present = {"dataset": True, "train": self.surrogate is not None, "invert": bool(self.optimizers),
                       "validate": self.validator is not None, "active": self.active is not None,
                       "report": bool(self.optimizers)}
            self.stages = [s for s in STAGES if present[s]]
        needs = {"train": ("surrogate",), "invert": ("surrogate",), "validate": ("validator",),
                 "active": ("active", "surrogate", "validator")}
        for stage, sections in needs.items():
            for section in sections:
                if stage in self.stages and not getattr(self, section):
                    raise ValueError(f"stage {stage!r} needs a {section!r} section")
        if "invert" in self.stages and not (self.optimizers or self.evaluation.baselines):  # baselines: targets only
            raise ValueError("stage 'invert' needs an 'optimizers' section or evaluation.baselines")
        for stage in ("validate", "active", "report"):
            if stage in self.stages and "invert" not in self.stages:
                raise ValueError(f"stage {stage!r} reads the targets that 'invert' picks: add 'invert' to stages")
        for label, block in self.optimizers.items():
            space = block.get("space", "raw")
            if space != "raw" and space not in self.latent_models:
                raise ValueError(
                    f"optimizers.{label}.space: {space!r} is neither 'raw' nor a latent model label"
                    f"{did_you_mean(str(space), self.latent_models)} (latent models: "
                    f"{', '.join(self.latent_models) or 'none'})"
                )
            if block.get("evaluator", "shared") not in ("shared", "own_head"):
                raise ValueError(f"optimizers.{label}.evaluator: must be 'shared' or 'own_head'")
            lam = block.get("uncertainty_penalty", 0.0)
            if isinstance(lam, bool) or not isinstance(lam, int | float) or lam < 0:
                raise ValueError(f"optimizers.{label}.uncertainty_penalty: must be a number >= 0")
            if lam and block.get("evaluator", "shared") != "shared":
                raise ValueError(f"optimizers.{label}.uncertainty_penalty: needs evaluator: shared (the ensemble's std)")
        groups = (set(self.optimizers), set(self.evaluation.baselines), set(self.evaluation.methods))
        clash = sorted((groups[0] & groups[1]) | (groups[2] & (groups[0] | groups[1])))
        if clash:
            raise ValueError(f"evaluation: label(s) {', '.join(clash)} used twice (optimizers, baselines, methods)")
        answers = [*self.optimizers, *self.evaluation.baselines]
        known = {*answers, *self.evaluation.methods}
        for label, cands in self.evaluation.best_of.items():
            if label in known or label == "noise_floor":
                raise ValueError(f"evaluation.best_of.{label}: label already used")
            bad = [c for c in cands if c not in known]
            if bad or not cands:
                raise ValueError(f"evaluation.best_of.{label}: {', '.join(bad) or 'no candidates'} "
                                 f"(candidates: optimisers, baselines or methods; not noise_floor)")
        for label, method in self.evaluation.methods.items():
            if method.start not in answers:
                raise ValueError(f"evaluation.methods.{label}.start: {method.start!r} is no optimiser or baseline"
                                 f"{did_you_mean(method.start, answers)} (labels: {', '.join(answers) or 'none'})")
        return self

    # -- helpers used by the runner ------------------------------------------------------------
    def plugin_blocks(self) -> list[tuple[str, str, PluginBlock]]:
        """Every plugin block as (path, kind, block-with-runner-keys-removed)."""
        blocks: list[tuple[str, str, PluginBlock]] = [("simulator", "simulator", self.simulator),
                                                       ("executor", "executor", self.executor)]
        if self.features is not None:
            blocks.append(("features", "feature_extractor", self.features))
        if self.surrogate is not None:
            blocks.append(("surrogate", "surrogate", self.surrogate))
        if self.validator is not None:
            blocks.append(("validator", "validator", self.validator))
        blocks += [(f"latent_models.{k}", "latent_model", b) for k, b in self.latent_models.items()]
        blocks += [(f"optimizers.{k}", "optimizer", optimizer_plugin_block(b)) for k, b in self.optimizers.items()]
        return blocks

    def evaluation_blocks(self) -> list[tuple[str, str, PluginBlock]]:
        """The evaluation section's baseline blocks as (path, kind, block); they are optimiser plugins."""
        return [(f"evaluation.baselines.{k}", "optimizer", b) for k, b in self.evaluation.baselines.items()]

    def section_dump(self, names: Iterable[str]) -> dict[str, Any]:
        """A JSON-able dump of the named sections (for stage fingerprints)."""
        data = self.model_dump(mode="json", by_alias=True)
        for section, fields in KEY_NEUTRAL_DEFAULTS.items():  # added later: at their defaults, keys unchanged
            block = data.get(section)
            if isinstance(block, dict):
                for name, default in fields.items():
                    if block.get(name) == default:
                        block.pop(name)
        polish = (data.get("active") or {}).get("polish")
        for one in polish if isinstance(polish, list) else [polish] if isinstance(polish, dict) else []:
            if not one.get("confirm"):  # added later: off, the polish's stage key is unchanged
                one.pop("confirm", None)
                one.pop("confirm_candidates", None)
        return {n: data.get(n) for n in names}


def optimizer_plugin_block(block: PluginBlock) -> PluginBlock:
    """An optimizer entry without the runner-level keys (``space``, ``evaluator``)."""
    return {k: v for k, v in block.items() if k not in OPTIMIZER_RUNNER_KEYS}


# ----------------------------------------------------------------------------------------------
# Loading and the two-pass validation
# ----------------------------------------------------------------------------------------------
def load_spec(path: str | Path, registry: Any = None) -> ExperimentSpec:
    """Read, parse and fully validate a YAML spec file. Raises :class:`SpecError`.

    The file must be a regular UTF-8 file within the size limit of :mod:`invphys.core.safe_yaml`.
    """
    p = Path(path)
    text = safe_yaml.read_text(p, what="spec")
    return parse_spec(text, source=str(p), registry=registry)


def parse_spec(text: str, source: str = "<spec>", registry: Any = None) -> ExperimentSpec:
    """Parse YAML text safely (:func:`invphys.core.safe_yaml.load`) and validate it (every pass)."""
    data, node = safe_yaml.load(text, source=source)
    if not isinstance(data, dict):
        raise SpecError(f"{source}: a spec is a YAML mapping with at least 'name' and 'simulator'")
    lines = _line_index(node)
    return validate_spec(data, source=source, lines=lines, registry=registry)


def validate_spec(data: dict[str, Any], source: str = "<spec>", lines: dict[tuple[str, ...], int] | None = None,
                  registry: Any = None, references: bool = True) -> ExperimentSpec:
    """Validate an already-parsed spec mapping: values (keys are strings, numbers finite), shape,
    plugin blocks, and (``references``) the cross-references :func:`validate_references` checks."""
    lines = lines or {}
    problems = spec_problems(data, registry, references)
    if problems:
        raise SpecError(_format(source, problems, lines), problems=problems, lines=lines)
    return ExperimentSpec.model_validate(data)


def spec_problems(data: dict[str, Any], registry: Any = None,
                  references: bool = True) -> list[tuple[tuple[str, ...], str]]:
    """Every problem of a parsed spec at once, as (path, message): values, shape, plugin blocks, and
    (``references``) the cross-references. A section that fails the shape check still has its plugin
    blocks checked; the cross-references need a spec whose shape is right."""
    problems = value_problems(data)
    try:  # keys that are not text are reported once, above; the shape check sees the rest
        spec: ExperimentSpec | None = ExperimentSpec.model_validate(_text_keys(data) if problems else data)
    except ValidationError as exc:
        spec = None
        problems += [(path, msg) for path, msg in _pydantic_problems(exc, ())
                     if not any(path[:len(q)] == q for q, _ in problems)]
    blocks = [*spec.plugin_blocks(), *spec.evaluation_blocks()] if spec is not None else _raw_plugin_blocks(data)
    plugin_problems = validate_plugin_blocks(blocks, registry)
    problems += [(path, msg) for path, msg in plugin_problems
                 if not any(path[:len(q)] == q or q[:len(path)] == path for q, _ in problems)]
    if spec is not None and references:  # each check copes with a block that failed above
        problems += [(path, msg) for path, msg in validate_references(spec, registry)
                     if not any(path[:len(q)] == q or q[:len(path)] == path for q, _ in problems)]
    return problems


def _text_keys(data: Any) -> Any:
    """``data`` without the mapping entries whose key is not text (at any depth)."""
    if isinstance(data, dict):
        return {k: _text_keys(v) for k, v in data.items() if isinstance(k, str)}
    if isinstance(data, list):
        return [_text_keys(v) for v in data]
    return data


def _raw_plugin_blocks(data: dict[str, Any]) -> list[tuple[str, str, Any]]:
    """The plugin blocks of a spec mapping whose shape failed, as :meth:`ExperimentSpec.plugin_blocks`
    gives them (what is not a mapping of blocks is left to the shape check's problems)."""
    def mapping(value: Any) -> dict[str, Any]:
        return value if isinstance(value, dict) else {}

    blocks: list[tuple[str, str, Any]] = []
    for section, kind in (("simulator", "simulator"), ("executor", "executor"), ("features", "feature_extractor"),
                          ("surrogate", "surrogate"), ("validator", "validator")):
        if isinstance(data.get(section), dict):
            blocks.append((section, kind, data[section]))
    blocks += [(f"latent_models.{k}", "latent_model", b) for k, b in mapping(data.get("latent_models")).items()
               if isinstance(b, dict)]
    blocks += [(f"optimizers.{k}", "optimizer", optimizer_plugin_block(b))
               for k, b in mapping(data.get("optimizers")).items() if isinstance(b, dict)]
    baselines = mapping(mapping(data.get("evaluation")).get("baselines"))
    blocks += [(f"evaluation.baselines.{k}", "optimizer", b) for k, b in baselines.items() if isinstance(b, dict)]
    return blocks


def value_problems(data: Any, path: tuple[str, ...] = ()) -> list[tuple[tuple[str, ...], str]]:
    """The one finite-number rule (and string keys): every float anywhere in a spec must be finite.

    YAML reads ``.inf`` and ``.nan`` as floats; no spec setting means anything by them, so they are
    refused wherever they appear, with their path.
    """
    problems: list[tuple[tuple[str, ...], str]] = []
    if isinstance(data, float) and not math.isfinite(data):
        problems.append((path, f"must be a finite number, not {data}"))
    elif isinstance(data, dict):
        for key, value in data.items():
            if not isinstance(key, str):
                problems.append(((*path, str(key)), f"the key {key!r} is not text; quote it"))
                continue
            problems += value_problems(value, (*path, key))
    elif isinstance(data, list):
        for i, item in enumerate(data):
            problems += value_problems(item, (*path, str(i)))
    return problems


def validate_plugin_blocks(spec: ExperimentSpec | list[tuple[str, str, Any]],
                           registry: Any = None) -> list[tuple[tuple[str, ...], str]]:
    """Pass 2: each plugin block by its plugin's Config (a spec's blocks, or a list of (path, kind, block)).
    Returns (path, message) problems."""
    from invphys import registry as registry_module

    reg = registry or registry_module.default_registry()
    problems: list[tuple[tuple[str, ...], str]] = []
    blocks = spec if isinstance(spec, list) else [*spec.plugin_blocks(), *spec.evaluation_blocks()]
    for dotted, kind, block in blocks:
        path = tuple(dotted.split("."))
        if not isinstance(block, dict) or "type" not in block:
            problems.append((path, "needs a 'type' field naming the plugin"))
            continue
        try:
            cls = reg.get(kind, str(block["type"]))
        except InvphysError as exc:
            problems.append(((*path, "type"), str(exc)))
            continue
        settings = {k: v for k, v in block.items() if k != "type"}
        try:
            cls.Config.model_validate(settings)
        except ValidationError as exc:
            problems += _pydantic_problems(exc, path, known=list(cls.Config.model_fields))
    return problems


def validate_references(spec: ExperimentSpec, registry: Any = None) -> list[tuple[tuple[str, ...], str]]:
    """Pass 3: what can be known without training, so that ``validate`` refuses what ``run`` would.

    Objective weights name features of the extractor; a ``warm_start`` names a goal-conditioned entry
    (or an existing ``policy_path``); ``dataset.path`` is a dataset (or ``if_missing: generate``); an
    explicit ``targets.n`` fits in the held-out split.
    """
    from invphys import registry as registry_module

    reg = registry or registry_module.default_registry()
    problems: list[tuple[tuple[str, ...], str]] = []
    if spec.objectives:
        names = _feature_names(spec, reg)
        if names is not None:
            for label, section in spec.objectives.items():
                for feature in section.weights:
                    if feature not in names:
                        problems.append((("objectives", label, "weights", feature),
                                         f"no feature {feature!r}.{did_you_mean(feature, names)} "
                                         f"Features: {', '.join(names)}"))
    classes: dict[str, Any] = {}
    for label, block in spec.optimizers.items():
        try:
            classes[label] = reg.get("optimizer", str(block["type"]))
        except Exception:  # reported by pass 2
            continue
    goal_conditioned = [k for k, c in classes.items() if getattr(c, "goal_conditioned", False)]
    for label, cls in classes.items():
        if "policy" not in getattr(cls, "Config", BaseModel).model_fields:
            continue
        block = spec.optimizers[label]
        policy, policy_path = block.get("policy"), block.get("policy_path")
        if policy is not None and policy not in goal_conditioned:
            problems.append((("optimizers", label, "policy"),
                             f"{policy!r} is not a goal-conditioned entry"
                             f"{did_you_mean(str(policy), goal_conditioned)} (goal-conditioned entries: "
                             f"{', '.join(goal_conditioned) or 'none'})"))
        elif policy is None and policy_path is None:
            problems.append((("optimizers", label), "needs `policy: <label of a goal-conditioned entry>`"))
        elif policy is None and not Path(str(policy_path)).is_dir():
            problems.append((("optimizers", label, "policy_path"), f"no saved policy at {policy_path!r}"))
    problems += _dataset_problems(spec)
    problems += _target_problems(spec, reg)
    return problems


def _target_problems(spec: ExperimentSpec, reg: Any) -> list[tuple[tuple[str, ...], str]]:
    """``targets.values`` / ``targets.file``: read and checked against the extractor's feature names as the
    invert stage will (a file that is missing, unreadable or names an unknown feature is refused now)."""
    from invphys.core.user_targets import from_mappings, read_target_file

    tg = spec.targets
    if tg.values is None and tg.file is None:
        return []
    names = _feature_names(spec, reg)
    where = ("targets", "values") if tg.values is not None else ("targets", "file")
    try:
        if tg.file is not None:
            p = Path(tg.file)
            if not p.is_file():
                kind = "a directory" if p.is_dir() else "not a regular file" if p.exists() else "absent"
                return [(where, f"{tg.file!r} is {kind}: name a JSON, YAML or CSV file of targets")]
            if names is not None:
                read_target_file(p, names)
            else:  # the features cannot be known without running: at least the file must be readable
                with p.open("rb"):
                    pass
        elif names is not None:
            from_mappings(tg.values or [], names, source="targets.values")
    except InvphysError as exc:
        return [(where, str(exc).removeprefix("targets.values: "))]
    except OSError as exc:
        return [(where, f"cannot read {tg.file!r}: {exc.strerror or exc}")]
    return []


def _feature_names(spec: ExperimentSpec, reg: Any) -> list[str] | None:
    """The extractor's feature names, or None when they cannot be known without running anything."""
    try:
        block = spec.features
        if block is None:
            default = reg.create("simulator", spec.simulator).default_feature_extractor()
            if default is None:
                return None
            block = {"type": default}
        return [str(n) for n in reg.create("feature_extractor", block).feature_names]
    except Exception:  # e.g. an extractor that needs a device: the run will say
        return None


def _dataset_problems(spec: ExperimentSpec) -> list[tuple[tuple[str, ...], str]]:
    ds = spec.dataset
    problems: list[tuple[tuple[str, ...], str]] = []
    rows: int | None = ds.n
    if ds.path is not None:
        p = Path(ds.path)
        if p.exists() and not p.is_dir():
            return [(("dataset", "path"), f"{ds.path!r} is a file, not a dataset directory")]
        if p.is_dir() and (p / "_metadata.json").is_file():
            broken = _store_problem(p)
            if broken:
                return [(("dataset", "path"), broken)]
            rows = _stored_ok_rows(p)
        elif p.is_dir() and any(not c.name.startswith(".") for c in p.iterdir()):
            return [(("dataset", "path"), f"{ds.path!r} is not an invphys dataset (no _metadata.json)")]
        elif not p.exists() and ds.if_missing == "error":
            return [(("dataset", "path"), f"no dataset at {ds.path!r} (set `if_missing: generate` to create it)")]
    if ds.extra_train:
        problems += _extra_store_problems(ds.path, ds.extra_train)
    stages = spec.stages or []
    tg = spec.targets
    explicit = "n" in tg.model_fields_set and getattr(tg, "values", None) is None and getattr(tg, "file", None) is None
    if "invert" in stages and explicit and rows is not None:
        held_out = max(1, round(rows * ds.test_fraction))
        if tg.n > held_out:
            problems.append((("targets", "n"), f"{tg.n} targets, but the held-out split has at most {held_out} "
                             f"rows ({rows} rows x test_fraction {ds.test_fraction:g})"))
    if "validate_n" in tg.model_fields_set and "n" in tg.model_fields_set and tg.validate_n > tg.n:
        problems.append((("targets", "validate"), f"{tg.validate_n} targets to validate, but targets.n is {tg.n}"))
    return problems


#: files that mark a directory as an invphys dataset store, and an inverter bundle's manifest
STORE_MARKERS: tuple[str, ...] = ("_metadata.json", "_manifest.json")
BUNDLE_MANIFEST = "manifest.yaml"


def output_problem(path: str | Path, option: str = "--out", store_ok: bool = False) -> str | None:
    """Why ``path`` cannot be an output directory (None when it can), before anything is written.

    Refused: a path that is a file, lies under a file, or runs through a symlink loop; a path in or under
    an inverter bundle (``manifest.yaml`` with ``format_version``); a path in or under a dataset store
    (``store_ok``: the path itself may be a store, as ``dataset generate --out`` resumes one).
    """
    import errno
    import os
    import stat

    given = Path(path)
    out = Path(os.path.abspath(given))
    chain = [out, *out.parents]
    try:  # links followed too: a link to a folder inside a store is inside that store
        real = given.resolve()
        chain += [place for place in (real, *real.parents) if place not in chain]
    except (OSError, RuntimeError):  # a symbolic-link loop: found below
        pass
    for level, place in enumerate(chain):
        shown = str(given) if level == 0 else str(place)
        try:
            st = os.stat(place)
        except FileNotFoundError:
            continue
        except OSError as exc:
            if exc.errno == errno.ELOOP:
                return (f"{option} {str(given)!r} is a symbolic-link loop" if level == 0 else
                        f"{option} {str(given)!r} runs through a symbolic-link loop ({shown!r})")
            if exc.errno == errno.ENOTDIR:
                continue  # a file above it: found at its own level
            return f"{option} {str(given)!r}: cannot look at {shown!r}: {exc.strerror or exc}"
        if not stat.S_ISDIR(st.st_mode):
            return (f"{option} {str(given)!r} is a file; name a new or existing directory" if level == 0
                    else f"{option} {str(given)!r} lies under {shown!r}, which is a file")
        if _is_bundle(place):
            where = "is" if level == 0 else f"lies inside {shown!r}, which is"
            return f"{option} {str(given)!r} {where} an inverter bundle; name a directory outside it"
        if any((place / m).is_file() for m in STORE_MARKERS) and not (store_ok and level == 0):
            where = "is" if level == 0 else f"lies inside {shown!r}, which is"
            return f"{option} {str(given)!r} {where} a dataset store; name a directory outside it"
    return None


def check_output_directory(path: str | Path, option: str = "--out", store_ok: bool = False) -> Path:
    """:func:`output_problem` as an :class:`InvphysError`; returns ``path``."""
    problem = output_problem(path, option, store_ok)
    if problem:
        raise InvphysError(problem)
    return Path(path)


def _is_bundle(directory: Path) -> bool:
    """True when ``directory`` holds an inverter bundle's manifest (a top-level ``format_version`` key)."""
    manifest = directory / BUNDLE_MANIFEST
    try:
        if not manifest.is_file():
            return False
        with manifest.open("rb") as fh:
            head = fh.read(65536)
    except OSError:
        return False
    return any(line.startswith(b"format_version:") for line in head.splitlines())


def _extra_store_problems(primary: str | None, extras: list[ExtraStore]) -> list[tuple[tuple[str, ...], str]]:
    """``dataset.extra_train``: each store readable, of the primary store's problem, and holding at
    least the ok rows its ``rows`` asks for."""
    from invphys.core.dataset import DatasetStore
    from invphys.core.dataset_union import check_extra_stores

    for i, extra in enumerate(extras):
        path = Path(extra.path)
        broken = _store_problem(path) if path.is_dir() else f"no dataset at {extra.path!r}"
        if broken:
            return [(("dataset", "extra_train", str(i)), broken)]
    if primary is None or not (Path(primary) / "_metadata.json").is_file():
        return [(("dataset", "extra_train"), "needs dataset.path: an existing primary store to join")]
    try:
        check_extra_stores(Path(primary), [e.path for e in extras])
    except InvphysError as exc:
        return [(("dataset", "extra_train"), str(exc).removeprefix("dataset.extra_train: "))]
    problems: list[tuple[tuple[str, ...], str]] = []
    for i, extra in enumerate(extras):
        if extra.rows is not None:
            held = DatasetStore(extra.path).ok_count()
            if held < extra.rows:
                problems.append((("dataset", "extra_train", str(i), "rows"),
                                 f"{extra.path!r} holds {held} ok rows, fewer than rows: {extra.rows}"))
    return problems


def _store_problem(path: Path) -> str | None:
    """Why the store at ``path`` cannot be read (None when it can): the check every reader makes."""
    from invphys.core.dataset import DatasetStore

    try:
        DatasetStore(path).keys()
    except InvphysError as exc:
        return str(exc)
    return None


def _stored_ok_rows(path: Path) -> int | None:
    """The ok-row count a store's metadata records (None when it does not say)."""
    try:
        import json

        totals = json.loads((path / "_metadata.json").read_text()).get("totals", {})
        ok = totals.get("ok") if isinstance(totals, dict) else None
        return int(ok) if isinstance(ok, int) and ok >= 0 else None
    except (OSError, ValueError, AttributeError):
        return None


def _pydantic_problems(exc: ValidationError, prefix: tuple[str, ...],
                       known: list[str] | None = None) -> list[tuple[tuple[str, ...], str]]:
    out = []
    suggested: set[tuple[str, ...]] = set()  # a misspelt key: its "missing" twin is not a second problem
    for err in exc.errors():
        loc = tuple(str(x) for x in err["loc"] if not str(x).startswith("function-after") and str(x) != "[key]")
        fields = known if known is not None else _section_fields(loc)
        if err["type"] == "extra_forbidden" and fields:
            match = did_you_mean(loc[-1], fields)
            if match:
                suggested.add((*loc[:-1], match.split("'")[1]))
        out.append(((*prefix, *loc), _message(err, fields), err["type"]))
    return [(path, msg) for path, msg, kind in out
            if not (kind == "missing" and path[len(prefix):] in suggested)]


def _section_fields(loc: tuple[str, ...]) -> list[str]:
    """The field names (aliases) of the spec model an error at ``loc`` (pass 1) sits in."""
    model: type[BaseModel] | None = None
    if len(loc) == 1:
        model = ExperimentSpec
    elif len(loc) == 2:
        sections: dict[str, type[BaseModel]] = {"dataset": DatasetSection, "targets": TargetsSection,
                                                 "report": ReportSection, "tracker": TrackerSection}
        model = sections.get(loc[0])
    elif len(loc) == 3 and loc[0] == "objectives":
        model = ObjectiveSection
    if model is None:
        return []
    return [f.alias or name for name, f in model.model_fields.items()]


def _message(err: Any, known: list[str] | None) -> str:
    kind, ctx = err["type"], err.get("ctx") or {}
    if kind == "greater_than":
        return f"must be > {ctx['gt']}"
    if kind == "greater_than_equal":
        return f"must be >= {ctx['ge']}"
    if kind == "less_than":
        return f"must be < {ctx['lt']}"
    if kind == "less_than_equal":
        return f"must be <= {ctx['le']}"
    if kind == "missing":
        return "required field is missing"
    if kind == "extra_forbidden":
        name = str(err["loc"][-1])
        hint = did_you_mean(name, known) if known else ""
        return f"unknown field.{hint}" if hint else "unknown field"
    if kind == "literal_error":
        return f"must be one of {ctx.get('expected', '')}"
    if kind == "value_error":
        return str(ctx.get("error", err["msg"]))
    return str(err["msg"][0].lower() + err["msg"][1:]) if err["msg"] else kind


def _format(source: str, problems: list[tuple[tuple[str, ...], str]],
            lines: dict[tuple[str, ...], int]) -> str:
    """One problem: one line ``source: path (line N): message``; several: a count, then one per line."""
    rows = []
    located = [(path, message, problem_line(path, lines)) for path, message in problems]
    located.sort(key=lambda item: item[2] or 0)  # in file order; file-wide problems first
    for path, message, line in located:
        where = ".".join(c if c.isprintable() else repr(c) for c in path) or "(top level)"
        rows.append(f"  {where}{f' (line {line})' if line else ''}: {message}")
    if len(rows) == 1:
        return f"{source}: {rows[0].strip()}"
    return f"{source}: {len(rows)} problems\n" + "\n".join(rows)


def problem_line(path: tuple[str, ...], lines: dict[tuple[str, ...], int]) -> int | None:
    """The YAML line of ``path`` or of its nearest enclosing key (None when unknown)."""
    for cut in range(len(path), 0, -1):
        if path[:cut] in lines:
            return lines[path[:cut]]
    return None


def _line_index(node: yaml.Node | None) -> dict[tuple[str, ...], int]:
    """Map each key path of a composed YAML document to its (1-based) line."""
    index: dict[tuple[str, ...], int] = {}

    def walk(n: yaml.Node, path: tuple[str, ...]) -> None:
        if isinstance(n, yaml.MappingNode):
            for key, value in n.value:
                p = (*path, str(key.value))
                index[p] = key.start_mark.line + 1
                walk(value, p)
        elif isinstance(n, yaml.SequenceNode):
            for i, item in enumerate(n.value):
                p = (*path, str(i))
                index[p] = item.start_mark.line + 1
                walk(item, p)

    if node is not None:
        walk(node, ())
    return index


#: the JSON Schema dialect and identifier of ``invphys schema``
SCHEMA_DIALECT = "https://json-schema.org/draft/2020-12/schema"
SCHEMA_ID = "urn:invphys:experiment-spec:1"
#: a ``type: package.module:Class`` plugin name (unpackaged code), as the registry accepts it
MODULE_CLASS_PATTERN = r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*:[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*$"


def _module_class_block(kind: str) -> dict[str, Any]:
    """The schema branch of a plugin named by ``module:Class``: its settings are checked by ``validate``."""
    return {"title": f"{kind}:module:Class", "type": "object", "required": ["type"],
            "properties": {"type": {"type": "string", "pattern": MODULE_CLASS_PATTERN}},
            "additionalProperties": True,
            "description": "a plugin named by its import path; `invphys validate` checks its settings"}


def json_schema(registry: Any = None) -> dict[str, Any]:
    """JSON Schema (draft 2020-12) of the spec, with each plugin block as a ``oneOf`` over the installed
    plugins' Configs and a ``module:Class`` branch for unpackaged plugins."""
    from invphys import registry as registry_module

    reg = registry or registry_module.default_registry()
    schema = {"$schema": SCHEMA_DIALECT, "$id": SCHEMA_ID, **ExperimentSpec.model_json_schema(by_alias=True)}
    defs = schema.setdefault("$defs", {})
    per_kind: dict[str, list[dict[str, Any]]] = {}
    for info in reg.infos():
        sub = info.cls.Config.model_json_schema()
        for k, v in sub.pop("$defs", {}).items():
            defs.setdefault(k, v)
        props = dict(sub.get("properties", {}))
        extra_keys = {"space": {"type": "string"}, "evaluator": {"enum": ["shared", "own_head"]},
                      "uncertainty_penalty": {"type": "number", "minimum": 0}} \
            if info.kind == "optimizer" else {}
        sub["properties"] = {"type": {"const": info.name}, **props, **extra_keys}
        sub["required"] = ["type", *sub.get("required", [])]
        sub["additionalProperties"] = False
        sub["title"] = f"{info.kind}:{info.name}"
        sub["description"] = (info.cls.__doc__ or "").strip().split("\n")[0]
        per_kind.setdefault(info.kind, []).append(sub)
    for kind, subs in per_kind.items():
        defs[f"{kind}_block"] = {"oneOf": [*subs, _module_class_block(kind)]}
    props = schema["properties"]
    single = {"simulator": "simulator", "features": "feature_extractor", "executor": "executor",
              "surrogate": "surrogate", "validator": "validator"}
    for section, kind in single.items():
        if kind in per_kind:
            ref = {"$ref": f"#/$defs/{kind}_block"}
            props[section] = {"anyOf": [ref, {"type": "null"}]} if section in ("features", "surrogate", "validator") else ref
    for section, kind in (("latent_models", "latent_model"), ("optimizers", "optimizer")):
        if kind in per_kind:
            props[section] = {"type": "object", "additionalProperties": {"$ref": f"#/$defs/{kind}_block"}}
    return schema

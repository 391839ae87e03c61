"""A Python function as a simulator (``invphys.simulator_from_function``, spec ``type: "module:function"``),
stage keys that follow the feature extractor (units, settings, version), and the docs' one-file example
(docs/writing-a-simulator.md, "A Python function as a simulator") run end to end: dataset, train, invert,
validate, report, export, then ``invphys invert`` on a target of one's own with the exported bundle."""

from __future__ import annotations

import importlib
import json
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import yaml

import invphys
from invphys import registry
from invphys.core.errors import InvphysError
from invphys.core.spec import parse_spec
from invphys.pipeline.runner import run_spec
from invphys.testing import (
    check_deterministic,
    check_feature_extractor,
    check_plugin_class,
    check_render,
    check_simulator,
)

ROOT = Path(__file__).resolve().parent.parent
GUIDE = ROOT / "docs" / "writing-a-simulator.md"

MODULE = '''
import numpy as np

import invphys

CALLS = []


def bowl(theta):
    """Two features of two parameters, one of them undefined (NaN) past a = 0.9, raising past b = 1.9."""
    CALLS.append(np.shape(theta))
    a, b = theta[:, 0], theta[:, 1]
    if (b > 1.9).any():
        raise ValueError("b too large")
    return np.stack([a + b, np.where(a > 0.9, np.nan, a * b)], axis=1)


def row(theta):
    """The same outputs, one row at a time (indexing a batch with it would give wrong answers)."""
    if theta[1] > 1.9:
        raise ValueError("b too large")
    return [theta[0] + theta[1], np.nan if theta[0] > 0.9 else theta[0] * theta[1]]


def plain(theta):
    """Not described in Python: a spec names its parameters and outputs."""
    return np.stack([theta[:, 0] * 2.0, theta[:, 1] - theta[:, 0]], axis=1)


PAIR = invphys.simulator_from_function(bowl, parameters={"a": (0, 1), "b": {"low": 1, "high": 2, "unit": "m"}},
                                       features=["s", "p"], units={"s": "m", "a": "s"}, vectorised=True)
ROW = invphys.simulator_from_function(row, parameters={"a": (0, 1), "b": (1, 2)}, features=["s", "p"],
                                      name="row_fn", vectorised=None)
'''


@pytest.fixture(autouse=True)
def _forget_registrations():
    """Unregister the function simulators a test registered (the registry is process-wide)."""
    from invphys.plugins.simulators import from_function

    before = set(from_function._REGISTERED)
    yield
    for name in set(from_function._REGISTERED) - before:
        registry.default_registry().unregister(from_function._REGISTERED.pop(name))


@pytest.fixture
def fnmod(tmp_path, monkeypatch):
    """A module of functions (``fnmod_<n>``) importable by name, freshly imported."""
    name = f"fnmod_{abs(hash(str(tmp_path))) % 10**8}"
    (tmp_path / f"{name}.py").write_text(MODULE)
    monkeypatch.syspath_prepend(str(tmp_path))
    module = importlib.import_module(name)
    yield module
    sys.modules.pop(name, None)


def test_a_described_function_is_a_registered_simulator_and_extractor(fnmod, tmp_path) -> None:
    sim_cls, ext_cls = fnmod.PAIR
    path = f"{fnmod.__name__}:bowl"
    assert "simulator_from_function" in invphys.__all__
    assert registry.get("simulator", path) is sim_cls is registry.get("simulator", "bowl")
    assert registry.get("feature_extractor", path) is ext_cls is registry.get("feature_extractor", "bowl")
    sim = registry.create("simulator", {"type": path})
    assert sim.default_feature_extractor() == path  # another process finds the extractor by the same path
    space = sim.parameter_space()
    assert space.names == ("a", "b") and [p.unit for p in space.parameters] == ["s", "m"]
    ext = registry.create("feature_extractor", {"type": sim.default_feature_extractor()})
    assert ext.feature_names == ("s", "p") and ext.feature_units == ("m", "")
    assert sim_cls.version.startswith("src-")  # a hash of the function's source
    for cls in (sim_cls, ext_cls):
        check_plugin_class(cls)
    ok = sim_cls()
    results = check_simulator(ok, n_runs=4)
    check_deterministic(ok)
    check_feature_extractor(ext, [r for r in results if r.ok])
    drawn = check_render(ok, next(r for r in results if r.ok).trajectory, tmp_path / "render", max_frames=1)
    assert [p.name for p in drawn.images] == ["outputs.png"]  # the outputs as labelled bars


def test_failures_are_recorded_per_run_and_never_depend_on_the_batch(fnmod) -> None:
    rows = np.array([[0.2, 1.5], [0.5, 1.95], [0.95, 1.2], [0.4, 1.1]])  # ok, raises, NaN, ok
    ext = fnmod.PAIR.extractor()
    for cls in (fnmod.PAIR.simulator, fnmod.ROW.simulator):
        res = cls().simulate(rows)
        assert [r.ok for r in res] == [True, False, False, True]
        assert res[1].failure == "exception: ValueError: b too large" and res[1].trajectory is None
        assert res[2].failure == "nan: non-finite output p"
        assert np.allclose(ext.extract(res[0].trajectory), [1.7, 0.3])
        alone = [cls().simulate(r[None])[0] for r in rows]  # one row per call: the same answers
        assert [r.ok for r in alone] == [True, False, False, True]
        assert np.allclose(ext.extract(alone[3].trajectory), ext.extract(res[3].trajectory))
    # the vectorised function is called on the batch, then row by row to isolate the failing row
    fnmod.CALLS.clear()
    fnmod.PAIR.simulator().simulate(rows)
    assert fnmod.CALLS == [(4, 2), (1, 2), (1, 2), (1, 2), (1, 2)]
    fnmod.CALLS.clear()
    fnmod.PAIR.simulator().simulate(rows[[0, 3]])
    assert fnmod.CALLS == [(2, 2)]


def test_undecided_calls_find_a_row_function_that_a_batch_would_fool(fnmod) -> None:
    sim = fnmod.ROW.simulator()  # vectorised=None: row(batch) would index rows, not columns
    assert sim.config.vectorised is None
    res = sim.simulate(np.array([[0.5, 1.5], [0.1, 1.1]]))
    assert sim._vectorised is False
    assert np.allclose(res[0].trajectory.series["features"].values, [[2.0, 0.75]])
    assert np.allclose(res[1].trajectory.series["features"].values, [[1.2, 0.11]])
    vec = fnmod.PAIR.simulator(vectorised=None)
    vec.simulate(np.array([[0.5, 1.5], [0.1, 1.1]]))
    assert vec._vectorised is True


def test_wrong_output_shapes_fail_the_run() -> None:
    def three(theta):
        return np.ones((len(theta), 3))

    sim_cls, _ = invphys.simulator_from_function(three, {"x": (0, 1)}, ["u", "v"], vectorised=True, name="three_out")
    res = sim_cls().simulate([[0.5]])
    assert not res[0].ok and res[0].failure.startswith("output: the function returned shape (1, 3), expected (1, 2)")


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"parameters": {"x": (1, 0)}}, "low"),
    ({"parameters": {"x": {"low": 0, "high": 1, "scale": "log"}}}, "unknown keys"),
    ({"parameters": {"x": {"low": 0, "high": 1, "log": True}}}, "positive"),
    ({"parameters": {"x": (0, 1, "m")}, "units": {"x": "s"}}, "unit"),
    ({"units": {"z": "m"}}, "neither parameters nor features"),
    ({"features": ["u", "u"]}, "repeat"),
    ({"feature_units": ["m"]}, "one unit per feature"),
    ({"features": {"u": "m", "v": ""}, "feature_units": {"u": "s"}}, "two units"),
    ({"name": "Not-A-Name"}, "lower-case identifier"),
])
def test_bad_descriptions_are_one_clear_error(kwargs, message) -> None:
    args = {"parameters": {"x": (0, 1)}, "features": ["u", "v"], **kwargs}
    with pytest.raises(InvphysError, match=message):
        invphys.simulator_from_function(lambda t: t, name=kwargs.get("name", "bad_desc"),
                                        **{k: v for k, v in args.items() if k != "name"})


def test_log_ranges_and_rich_parameters() -> None:
    from invphys.core.params import Parameter

    sim_cls, ext_cls = invphys.simulator_from_function(
        lambda t: t[:, :2], name="rich_fn", vectorised=True, features={"u": "Pa", "v": ""}, feature_units={"v": "1"},
        parameters={"e": {"low": 1e3, "high": 1e6, "log": True, "unit": "Pa", "description": "stiffness"},
                    "nu": Parameter("nu", 0.1, 0.45)})
    space = sim_cls().parameter_space()
    assert space.parameters[0].log and space.parameters[0].description == "stiffness"
    assert np.allclose(space.denormalize(np.array([[0.5, 0.0]])), [[10**4.5, 0.1]])
    assert ext_cls().feature_units == ("Pa", "1")


def test_a_name_taken_by_another_plugin_is_refused_and_a_redescription_replaces_its_own(fnmod) -> None:
    from invphys.core.interfaces import Simulator

    class Taken(Simulator):
        """Occupies a name."""

        name = "taken_name"

        def parameter_space(self):  # pragma: no cover - never called
            raise NotImplementedError

        def simulate(self, params, on_result=None):  # pragma: no cover - never called
            raise NotImplementedError

    with registry.registered(Taken), pytest.raises(InvphysError, match="another name"):
        invphys.simulator_from_function(fnmod.plain, {"x": (0, 1)}, ["u"], name="taken_name")
    assert "taken_name" not in registry.names("simulator")  # the failed registration left nothing
    first, _ = invphys.simulator_from_function(fnmod.plain, {"x": (0, 1)}, ["u"], name="again_fn")
    second, _ = invphys.simulator_from_function(fnmod.plain, {"x": (0, 2)}, ["u"], name="again_fn")
    assert registry.get("simulator", "again_fn") is second is not first


def test_a_plain_function_is_described_by_its_spec_blocks(fnmod, tmp_path) -> None:
    path = f"{fnmod.__name__}:plain"
    text = textwrap.dedent(f"""\
        name: plain-fn
        seed: 0
        stages: [dataset]
        simulator:
          type: "{path}"
          parameters: {{a: [0, 1, s], b: {{low: 1, high: 2, unit: m}}}}
          vectorised: true
        features: {{type: "{path}", names: [twice, diff], units: {{twice: s}}}}
        dataset: {{n: 8, batch_size: 4}}
        """)
    run_spec(parse_spec(text), tmp_path / "run", progress=False)
    from invphys.core.dataset import DatasetStore

    data = DatasetStore(tmp_path / "run" / "dataset" / "store").arrays(ok_only=True)
    assert len(data.theta) == 8 and list(data.feature_names) == ["twice", "diff"]
    assert np.allclose(data.y[:, 0], 2 * data.params[:, 0]) and np.allclose(data.y[:, 1], data.params[:, 1] - data.params[:, 0])
    with pytest.raises(InvphysError, match="parameters"):
        registry.create("simulator", {"type": path})
    with pytest.raises(InvphysError, match="not an optimizer plugin class"):
        registry.get("optimizer", path)
    with pytest.raises(InvphysError):
        registry.get("simulator", "os:getcwd")  # only pure-Python functions defined in the named module


# ------------------------------------------------------------------------------------------------
# Stage keys follow the feature extractor
# ------------------------------------------------------------------------------------------------
def _events(text: str, out: Path) -> list[tuple[str, str]]:
    events: list[tuple[str, str]] = []
    run_spec(parse_spec(text), out, progress=False, on_stage=lambda s, status, _: events.append((s, status)))
    return events


def test_adding_units_reruns_the_stages_that_record_them(fnmod, tmp_path) -> None:
    """The issue's friction: units added to the extractor left ``train`` (which writes the bundle and its
    units) cached; now the dataset stage re-runs (every run already stored) and so does everything after it."""
    text = textwrap.dedent(f"""\
        name: units
        seed: 0
        stages: [dataset, train]
        simulator: {{type: "{fnmod.__name__}:bowl"}}
        dataset: {{n: 24, batch_size: 24}}
        surrogate: {{type: mlp, hidden: [8, 8, 8], max_epochs: 2}}
        """)
    out = tmp_path / "run"
    assert _events(text, out) == [("dataset", "start"), ("dataset", "done"), ("train", "start"), ("train", "done")]
    assert _events(text, out) == [("dataset", "cached"), ("train", "cached")]
    manifest = yaml.safe_load((out / "inverter" / "manifest.yaml").read_text())
    assert manifest["features"]["units"] == ["m", ""]
    # the same function re-described with one more unit: nothing in the spec changed
    invphys.simulator_from_function(fnmod.bowl, parameters={"a": (0, 1), "b": {"low": 1, "high": 2, "unit": "m"}},
                                    features=["s", "p"], units={"s": "m", "a": "s", "p": "m^2"}, vectorised=True,
                                    version=fnmod.PAIR.simulator.version)
    assert _events(text, out) == [("dataset", "start"), ("dataset", "done"), ("train", "start"), ("train", "done")]
    assert json.loads((out / "dataset" / "summary.json").read_text())["ran"] == 0  # nothing re-simulated
    manifest = yaml.safe_load((out / "inverter" / "manifest.yaml").read_text())
    assert manifest["features"]["units"] == ["m", "m^2"]
    assert _events(text, out) == [("dataset", "cached"), ("train", "cached")]


def test_the_stale_reason_names_the_extractor() -> None:
    from invphys.pipeline import cache

    before = {"components": {"spec": "a", "plugins": {cache.EXTRACTOR_ENTRY: "x@/1", "surrogate": "mlp"}}}
    now = {"spec": "a", "plugins": {cache.EXTRACTOR_ENTRY: "x@/2", "surrogate": "mlp"}}
    assert cache.stale_reason(before, now) == "the feature extractor (settings, units or version) changed"


def test_an_extractor_setting_changes_the_key_of_a_stage_that_reads_the_dataset(fnmod) -> None:
    from invphys.pipeline import cache

    base = f'name: k\nsimulator: {{type: "{fnmod.__name__}:bowl"}}\nsurrogate: {{type: mlp}}\n'
    reg = registry.default_registry()
    keys = []
    for features in ("", f'features: {{type: "{fnmod.__name__}:bowl", units: {{s: km}}}}\n'):
        spec = parse_spec(base + features)
        keys.append(cache.plugin_versions(spec, ("dataset", "surrogate"), reg))  # the train stage's sections
    assert keys[0][cache.EXTRACTOR_ENTRY] != keys[1][cache.EXTRACTOR_ENTRY]
    assert cache.EXTRACTOR_ENTRY not in cache.plugin_versions(parse_spec(base), ("report",), reg)


# ------------------------------------------------------------------------------------------------
# The docs' example, end to end
# ------------------------------------------------------------------------------------------------
def guide_section() -> dict[str, list[str]]:
    """The code blocks of the guide's function-simulator section, by language, in order."""
    text = GUIDE.read_text()
    start = text.index("## A Python function as a simulator")
    section = text[start:text.index("\n## ", start + 5)]
    blocks: dict[str, list[str]] = {}
    for lang, body in re.findall(r"^```(\w+)\n(.*?)^```$", section, re.S | re.M):
        blocks.setdefault(lang, []).append(body)
    return blocks


def _cli(cwd: Path, line: str) -> subprocess.CompletedProcess[str]:
    args = line.split()
    assert args[0] == "invphys"
    return subprocess.run([sys.executable, "-m", "invphys.cli", *args[1:]], cwd=cwd, text=True,
                          capture_output=True, timeout=300)


def test_the_guide_example_is_short_and_complete() -> None:
    blocks = guide_section()
    assert len(blocks["python"]) == 1 and len(blocks["bash"]) == 1
    code = [ln for ln in blocks["python"][0].splitlines() if ln.strip() and not ln.lstrip().startswith(("#", '"""'))]
    assert len(code) <= 26  # "a 20-line example": the function and its description
    assert "numpy" in blocks["python"][0] and "invphys.simulator_from_function" in blocks["python"][0]
    commands = blocks["bash"][0].splitlines()
    assert [c.split()[1] for c in commands] == ["run", "export", "invert"]


def test_the_guide_example_runs_the_pipeline_export_and_invert(tmp_path) -> None:
    """The section's file, spec and commands, at smaller sizes (~20 s on a loaded 2-core CPU)."""
    blocks = guide_section()
    (tmp_path / "projectile.py").write_text(blocks["python"][0])
    spec = blocks["yaml"][0]
    for old, new in (("n: 400", "n: 120"), ("max_epochs: 200", "max_epochs: 60"), ("budget: 400", "budget: 150")):
        assert old in spec
        spec = spec.replace(old, new)
    (tmp_path / "projectile.yaml").write_text(spec)
    run, export, invert = blocks["bash"][0].splitlines()
    res = _cli(tmp_path, run)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-3000:]
    out = tmp_path / "runs" / "projectile"
    validation = json.loads((out / "validate" / "validation.json").read_text())
    cma = [v for v in validation if v["optimizer"] == "cma_es"]
    assert len(cma) == 4 and not any(v["failure"] for v in cma)
    assert np.mean([v["r_actual"] for v in cma]) > 0.6  # measured 0.92 at full size, 0.91 at these sizes
    assert (out / "report" / "report.md").is_file()
    res = _cli(tmp_path, export)
    assert res.returncode == 0, res.stderr[-3000:]
    res = _cli(tmp_path, invert + " --json")
    assert res.returncode == 0, res.stderr[-3000:]
    answer = json.loads(res.stdout)["results"][0]
    best = answer["candidates"][0]
    assert set(best["parameters"]) == {"speed", "angle", "drag", "height"}
    assert best["parameters"]["speed"]["unit"] == "m/s"
    assert best["r_actual"] > 0.6, best  # re-simulated by the function itself (--validate)


def test_the_guide_spec_form_describes_a_plain_function(tmp_path, monkeypatch) -> None:
    """The section's second spec: the same function without invphys.simulator_from_function."""
    blocks = guide_section()
    module = blocks["python"][0].split("\n\ninvphys.simulator_from_function(")[0]
    name = f"projectile_plain_{abs(hash(str(tmp_path))) % 10**8}"
    (tmp_path / f"{name}.py").write_text(module)
    monkeypatch.syspath_prepend(str(tmp_path))
    text = blocks["yaml"][0].split("simulator:")[0] + blocks["yaml"][1].replace("projectile:projectile", f"{name}:projectile")
    text = re.sub(r"stages: \[.*\]", "stages: [dataset]", text) + "dataset: {n: 20, batch_size: 10}\n"
    text = text.replace("dataset: {n: 400, batch_size: 100, sampler: sobol}\n", "")
    run_spec(parse_spec(text), tmp_path / "run", progress=False)
    from invphys.core.dataset import DatasetStore

    data = DatasetStore(tmp_path / "run" / "dataset" / "store").arrays(ok_only=True)
    assert len(data.theta) == 20 and list(data.feature_names) == ["range", "apex", "flight_time", "impact_speed"]
    assert (data.y[:, 1] >= data.params[:, 3]).all()  # the apex is at least the launch height
    sys.modules.pop(name, None)

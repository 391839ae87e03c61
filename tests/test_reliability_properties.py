"""Property-based tests (hypothesis): generated junk thrown at the spec loader, the parameter parser and
the store ends in a clean InvphysError (or a valid result), never another exception or a partial write."""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_dataset_toy import SIM

from invphys.core.dataset import DatasetError, DatasetStore, Row, RunIdentity, row_key
from invphys.core.errors import InvphysError, ParameterRangeError
from invphys.core.params import Parameter, ParameterSpace
from invphys.core.results import RunStats, SimulationResult
from invphys.core.spec import ExperimentSpec, load_spec, parse_spec

FAST = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])

scalars = st.one_of(st.none(), st.booleans(), st.integers(-10**20, 10**20), st.floats(allow_nan=True),
                    st.text(max_size=12))
keys = st.one_of(st.sampled_from(["name", "simulator", "dataset", "type", "n", "seed", "optimizers", "stages",
                                  "space", "budget", "weights", "objectives", "targets", "batch_size", "path"]),
                 st.text(max_size=8))
values = st.recursive(scalars, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                      st.dictionaries(keys, inner, max_size=5)), max_leaves=25)


def spec_like():
    base = {"name": "p", "simulator": {"type": SIM, "n_frames": 10}, "dataset": {"n": 8}}
    return st.dictionaries(keys, values, max_size=6).map(lambda extra: {**base, **extra})


@FAST
@given(spec_like())
def test_spec_loader_on_generated_mappings(data) -> None:
    try:
        text = yaml.safe_dump(data, allow_unicode=True)
    except yaml.YAMLError:
        return
    try:
        spec = parse_spec(text, source="gen.yaml")
    except InvphysError as exc:
        assert str(exc).startswith("gen.yaml: ") and "Traceback" not in str(exc)
        return
    assert isinstance(spec, ExperimentSpec)
    for number in _floats(spec.model_dump()):
        assert math.isfinite(number)


@FAST
@given(st.binary(max_size=300))
def test_spec_loader_on_generated_bytes(blob: bytes) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "junk.yaml"
        path.write_bytes(blob)
        with pytest.raises(InvphysError):
            load_spec(path)  # no bytes make a valid spec without 'simulator'


@FAST
@given(st.text(max_size=200))
def test_spec_loader_on_generated_text(text: str) -> None:
    try:
        parse_spec(text, source="t.yaml")
    except InvphysError:
        pass


def _floats(obj):
    if isinstance(obj, float):
        yield obj
    elif isinstance(obj, dict):
        for v in obj.values():
            yield from _floats(v)
    elif isinstance(obj, list | tuple):
        for v in obj:
            yield from _floats(v)


SPACE = ParameterSpace((Parameter("E", 50.0, 8000.0, log=True, unit="Pa"), Parameter("sigma_s", 0.05, 0.5),
                        Parameter("m", 0.5, 2.0)))
param_values = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-10**6, 10**6),
                         st.text(max_size=5), st.booleans(), st.none())


@FAST
@given(st.dictionaries(st.one_of(st.sampled_from(SPACE.names), st.text(max_size=6)), param_values, max_size=5))
def test_parameter_parser_reports_every_offender_as_given(values) -> None:
    try:
        x = SPACE.from_mapping(values, defaults=SPACE.to_mapping(SPACE.center()))
    except ParameterRangeError as exc:
        msg = str(exc)
        assert "\n" not in msg
        merged = {**SPACE.to_mapping(SPACE.center()), **values}
        if "unknown" in msg or "not a number" in msg:
            return
        for p in SPACE.parameters:  # every out-of-range parameter named, its value not rounded onto a bound
            v = float(merged[p.name])
            if not (math.isfinite(v) and p.low <= v <= p.high):
                assert f"{p.name} = " in msg
                if math.isfinite(v) and not v.is_integer():
                    assert repr(v) in msg
        return
    assert all(p.low <= v <= p.high for p, v in zip(SPACE.parameters, x, strict=True))


def test_a_value_just_below_a_bound_is_not_rounded_onto_it() -> None:
    with pytest.raises(ParameterRangeError) as err:
        SPACE.check([9000.0, 0.049999999, 3.0])
    assert str(err.value) == ("E = 9000 is outside its range [50, 8000] Pa; sigma_s = 0.049999999 is outside "
                              "its range [0.05, 0.5]; m = 3 is outside its range [0.5, 2]")


IDENT = RunIdentity("toy", "tiny", "numpy", "1", "cfg")


def _row(theta) -> Row:
    stats = RunStats(backend="numpy", device="cpu", preset="tiny", simulator="toy", simulator_version="1")
    res = SimulationResult(params=np.asarray(theta), ok=True, stats=stats, features=np.array([1.0, 2.0]))
    return Row(key=row_key(theta, IDENT), sample_index=0, theta=np.asarray(theta), params=np.asarray(theta),
               result=res)


thetas = st.lists(st.tuples(st.sampled_from([0.0, 0.25, 0.5, 0.75, 1.0]), st.sampled_from([0.0, 0.5, 1.0])),
                  min_size=0, max_size=4)


@settings(max_examples=25, deadline=None)
@given(st.lists(thetas, max_size=5), st.integers(0, 400), st.binary(min_size=1, max_size=8))
def test_store_appends_and_corruption(batches, offset, junk) -> None:
    """Batches that repeat a key are refused whole (nothing written); corrupt bytes are named, never read."""
    with tempfile.TemporaryDirectory() as tmp:
        store = DatasetStore(Path(tmp) / "s")
        stored: set[str] = set()
        with store.writer():
            store.create_or_check({"identity": IDENT.to_dict(), "param_names": ["a", "b"],
                                   "feature_names": ["f1", "f2"]})
            for batch in batches:
                rows = [_row(list(t)) for t in batch]
                keys = [r.key for r in rows]
                try:
                    store.append(rows)
                except DatasetError:
                    assert len(set(keys)) < len(keys) or stored.intersection(keys)
                else:
                    stored.update(keys)
                assert store.keys() == stored and store.verify().ok
        parts = store.parts()
        if not parts:
            return
        victim = parts[0]
        data = bytearray(victim.read_bytes())
        pos = offset % len(data)
        data[pos:pos + len(junk)] = junk
        if bytes(data) == victim.read_bytes():
            return
        victim.write_bytes(bytes(data))
        assert [p.kind for p in store.verify().problems] == ["corrupt"]
        with pytest.raises(DatasetError, match="corrupt"):
            store.frame()

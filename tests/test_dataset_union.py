"""Training on several stores (``dataset.extra_train``, each capped or not) and early stopping on a training carve.

Real toy-simulator stores made by the dataset stage; real training; the held-out rows must stay the
primary store's and never reach a model while it fits.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from invphys.core.errors import SpecError

TOY = '{type: "test_dataset_toy:ToyOscillator", substeps: SUB}'


def make_store(root, name: str, n: int, seed: int, substeps: int = 1):
    from invphys.core.spec import parse_spec
    from invphys.pipeline.runner import run_spec

    spec = parse_spec(f"name: {name}\nseed: {seed}\nstages: [dataset]\n"
                      f"simulator: {TOY.replace('SUB', str(substeps))}\n"
                      f"dataset: {{n: {n}, batch_size: 32, sampler: uniform}}\n")
    run_spec(spec, root / name, progress=False)
    return root / name / "dataset" / "store"


def train_spec(primary, extras=(), early_stopping: str = "held_out") -> str:
    extra = ", ".join(f'"{e}"' for e in extras)
    return (f"name: union\nseed: 3\nstages: [dataset, train]\nsimulator: {TOY.replace('SUB', '1')}\n"
            f'dataset: {{path: "{primary}", extra_train: [{extra}], early_stopping: {early_stopping}}}\n'
            "surrogate: {type: mlp, max_epochs: 30, patience: 10, hidden: [32, 32, 16], val_fraction: 0.25}\n")


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    root = tmp_path_factory.mktemp("stores")
    return {"a": make_store(root, "a", 80, seed=1), "b": make_store(root, "b", 40, seed=7),
            "foreign": make_store(root, "foreign", 16, seed=1, substeps=2)}


def test_extra_rows_join_training_only_and_the_held_out_split_is_unchanged(stores, tmp_path) -> None:
    from invphys import registry
    from invphys.core.dataset import DatasetStore
    from invphys.core.spec import parse_spec
    from invphys.pipeline.runner import StageContext, run_spec

    def context(spec_text: str, out):
        spec = parse_spec(spec_text)
        return spec, StageContext(spec=spec, out=out, stage="train", registry=registry.default_registry(),
                                  console=None, progress=False)

    _, alone = context(train_spec(stores["a"]), tmp_path / "alone")
    spec, joined = context(train_spec(stores["a"], [stores["b"]], "training_carve"), tmp_path / "joined")
    tr0, te0 = alone.split()
    tr1, te1 = joined.split()
    d0, d1 = alone.dataset(), joined.dataset()
    n_b = len(DatasetStore(stores["b"]).arrays(ok_only=True))  # the toy fails some runs on purpose
    assert n_b > 20 and len(d1) == len(d0) + n_b and d1.fingerprint != d0.fingerprint
    assert np.array_equal(d0.keys[te0], d1.keys[te1])  # the same held-out rows (so the same targets)
    assert set(d1.keys[tr1]) == set(d0.keys[tr0]) | set(d1.keys[len(d0):])
    assert not set(d1.keys[tr1]) & set(d1.keys[te1])
    # the yardstick too: the scales (farthest-point targets, every R) ignore the extra rows
    assert np.array_equal(alone.scales(), joined.scales())
    from invphys.core.objectives import percentile_scales
    assert not np.allclose(percentile_scales(d1.y[tr1]), joined.scales())  # the extras would have moved them
    from invphys.core.target_selection import select_targets
    from invphys.pipeline.stages.invert import select

    targets = "targets: {n: 6, selection: farthest_point}\n"
    _, alone_t = context(train_spec(stores["a"]) + targets, tmp_path / "alone_t")
    _, joined_t = context(train_spec(stores["a"], [stores["b"]]) + targets, tmp_path / "joined_t")
    far = joined_t.dataset().y
    far[joined_t.primary_rows():] = far[joined_t.primary_rows():] * np.linspace(50.0, 0.02, far.shape[1])  # extra rows, another spread
    rows = select(joined_t)["rows"]
    assert len(rows) == 6 and rows == select(alone_t)["rows"]  # farthest-point targets: the same rows
    assert rows != select_targets(far, te1, 6, "farthest_point").tolist()  # standardised by all rows: others

    s = run_spec(spec, tmp_path / "joined", progress=False)["train"]
    assert s["n_train"] == len(tr0) + n_b and s["n_test"] == len(te0)
    assert s["early_stopping"] == "training_carve"
    metrics = s["surrogate"]["metrics"]
    assert metrics["n_train"] + metrics["n_val"] == s["n_train"]  # validation rows carved from training rows
    assert "early stopping on carves of the training rows" in (tmp_path / "joined" / "train" / "metrics.md").read_text()

    held = run_spec(parse_spec(train_spec(stores["a"])), tmp_path / "held", progress=False)["train"]
    assert held["surrogate"]["metrics"]["n_val"] == held["n_test"]  # the paper's protocol: stops on held-out rows


def test_defaults_leave_stage_keys_unchanged(stores) -> None:
    from invphys.core.spec import parse_spec

    plain = parse_spec(train_spec(stores["a"]).replace(", extra_train: [], early_stopping: held_out", ""))
    explicit = parse_spec(train_spec(stores["a"]))
    assert plain.section_dump(["dataset"]) == explicit.section_dump(["dataset"])
    assert "extra_train" not in plain.section_dump(["dataset"])["dataset"]


def test_adding_a_store_re_runs_training(stores, tmp_path) -> None:
    from invphys.core.spec import parse_spec
    from invphys.pipeline.runner import run_spec

    out = tmp_path / "run"
    run_spec(parse_spec(train_spec(stores["a"])), out, progress=False)
    seen: list[tuple[str, str]] = []
    run_spec(parse_spec(train_spec(stores["a"], [stores["b"]])), out, progress=False,
             on_stage=lambda stage, status, _: seen.append((stage, status)))
    assert ("train", "start") in seen


def test_foreign_or_missing_extra_stores_are_refused(stores, tmp_path) -> None:
    from invphys.core.spec import parse_spec

    with pytest.raises(SpecError, match="config hash"):
        parse_spec(train_spec(stores["a"], [stores["foreign"]]))
    with pytest.raises(SpecError, match="no dataset at"):
        parse_spec(train_spec(stores["a"], [tmp_path / "nothing"]))
    with pytest.raises(SpecError, match="listed twice"):
        parse_spec(train_spec(stores["a"], [stores["b"], stores["b"]]))


def test_cli_says_one_line_and_exits_2(stores, tmp_path) -> None:
    spec = tmp_path / "spec.yaml"
    spec.write_text(train_spec(stores["a"], [stores["foreign"]]))
    proc = subprocess.run([sys.executable, "-m", "invphys.cli", "validate", str(spec)],
                          capture_output=True, text=True, cwd=str(tmp_path),
                          env={**__import__("os").environ, "PYTHONPATH": str(__import__("pathlib").Path(__file__).parent)})
    assert proc.returncode == 2, proc.stderr
    assert "extra_train" in proc.stderr and "Traceback" not in proc.stderr


# -- a row cap per extra store ({path, rows: N}): a result on a growing store re-runs exactly ----------
def capped_spec(primary, entry: str, stages: str = "[dataset, train]") -> str:
    return train_spec(primary).replace("stages: [dataset, train]", f"stages: {stages}").replace(
        "extra_train: []", f"extra_train: [{entry}]")


def first_ok_keys(store, n: int) -> list[str]:
    """The first ``n`` ok rows' keys in store order, read straight from the parts the manifest lists."""
    import pyarrow.parquet as pq

    from invphys.core.dataset import DatasetStore

    keys: list[str] = []
    for part in DatasetStore(store).manifest["parts"]:
        table = pq.read_table(store / part["name"], columns=["key", "status"])
        keys += [k for k, s in zip(table.column("key").to_pylist(), table.column("status").to_pylist(), strict=True)
                 if s == "ok"]
    return keys[:n]


def extra_rows(spec_text: str, out):
    """(keys of the extra store's rows in the joined dataset, the joined fingerprint, the data fingerprint)."""
    from invphys import registry
    from invphys.core.spec import parse_spec
    from invphys.pipeline.runner import StageContext

    ctx = StageContext(spec=parse_spec(spec_text), out=out, stage="train", registry=registry.default_registry(),
                       console=None, progress=False)
    data = ctx.dataset()
    return sorted(data.keys[ctx.primary_rows():].tolist()), data.fingerprint, ctx.data_fingerprint()


def test_a_capped_store_gives_its_first_rows_and_growing_it_changes_neither_rows_nor_fingerprints(stores, tmp_path):
    from invphys.core.dataset import DatasetStore, keys_fingerprint

    root = tmp_path / "stores"
    grow = make_store(root, "grow", 40, seed=7)
    held = DatasetStore(grow).ok_count()
    assert 20 < held < 40  # the toy fails some runs: the cap counts ok rows
    n = held - 3
    capped, exact = f'{{path: "{grow}", rows: {n}}}', f'{{path: "{grow}", rows: {held}}}'
    before = {name: extra_rows(capped_spec(stores["a"], entry), tmp_path / name)
              for name, entry in [("capped", capped), ("exact", exact), ("plain", f'"{grow}"')]}
    assert before["capped"][0] == sorted(first_ok_keys(grow, n)) and len(before["capped"][0]) == n
    # a cap at every ok row the store holds: the same rows, and the fingerprint the store has now (its
    # parts are the ones holding those rows); a smaller cap: other rows, another fingerprint
    assert before["exact"] == before["plain"]
    assert before["capped"][1] != before["plain"][1] and before["capped"][2] != before["plain"][2]

    make_store(root, "grow", 72, seed=7)  # the same store grows (new parts appended)
    assert DatasetStore(grow).ok_count() > held + 10
    after = {name: extra_rows(capped_spec(stores["a"], entry), tmp_path / f"{name}2")
             for name, entry in [("capped", capped), ("exact", exact), ("plain", f'"{grow}"')]}
    assert after["capped"] == before["capped"] and after["exact"] == before["exact"]
    assert after["plain"][0] != before["plain"][0]
    assert after["plain"][1] != before["plain"][1] and after["plain"][2] != before["plain"][2]
    assert DatasetStore(grow).arrays(first_ok=n).fingerprint == keys_fingerprint(first_ok_keys(grow, n))
    assert DatasetStore(grow).content_fingerprint(n - 1) != DatasetStore(grow).content_fingerprint(n)


def test_growing_a_capped_store_keeps_stages_cached_and_changing_the_cap_re_runs_them(stores, tmp_path):
    from invphys.core.spec import parse_spec
    from invphys.pipeline.runner import run_spec

    root = tmp_path / "stores"
    grow = make_store(root, "grow", 40, seed=5)
    out = tmp_path / "run"

    def stages(rows: int) -> dict[str, str]:
        seen: dict[str, str] = {}
        run_spec(parse_spec(capped_spec(stores["a"], f'{{path: "{grow}", rows: {rows}}}')), out, progress=False,
                 on_stage=lambda stage, status, _: seen.setdefault(stage, status))
        return seen

    assert stages(12)["train"] == "start"
    make_store(root, "grow", 72, seed=5)
    assert stages(12)["train"] == "cached"  # the store grew past the cap: the same rows, the same model
    assert stages(13)["train"] == "start"


def test_a_cap_beyond_the_store_is_one_clear_spec_problem(stores, tmp_path) -> None:
    import jsonschema
    import yaml

    from invphys.core.dataset import DatasetStore
    from invphys.core.spec import json_schema, parse_spec

    held = DatasetStore(stores["b"]).ok_count()
    with pytest.raises(SpecError, match=rf"dataset\.extra_train\.0\.rows \(line 5\): '{stores['b']}' holds "
                                        rf"{held} ok rows, fewer than rows: {held + 1}"):
        parse_spec(capped_spec(stores["a"], f'{{path: "{stores["b"]}", rows: {held + 1}}}'))
    with pytest.raises(SpecError, match=r"dataset\.extra_train\.0\.rows .*must be > 0"):
        parse_spec(capped_spec(stores["a"], f'{{path: "{stores["b"]}", rows: 0}}'))
    with pytest.raises(SpecError, match=r"dataset\.extra_train\.0\.path .*required"):
        parse_spec(capped_spec(stores["a"], "{rows: 3}"))
    spec = tmp_path / "spec.yaml"
    spec.write_text(capped_spec(stores["a"], f'{{path: "{stores["b"]}", rows: {held + 1}}}'))
    proc = subprocess.run([sys.executable, "-m", "invphys.cli", "validate", str(spec)],
                          capture_output=True, text=True, cwd=str(tmp_path),
                          env={**__import__("os").environ, "PYTHONPATH": str(__import__("pathlib").Path(__file__).parent)})
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert f"holds {held} ok rows, fewer than rows: {held + 1}" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1
    # the JSON Schema takes both forms of an entry
    validator = jsonschema.Draft202012Validator(json_schema())
    both = capped_spec(stores["a"], f'"{stores["b"]}", {{path: "{stores["b"]}", rows: 5}}')
    assert not list(validator.iter_errors(yaml.safe_load(both)))
    assert list(validator.iter_errors(yaml.safe_load(capped_spec(stores["a"], f'{{path: "{stores["b"]}", rows: 0}}'))))


def test_a_plain_path_is_still_every_row_and_keeps_stage_keys(stores) -> None:
    from invphys.core.spec import parse_spec

    plain = parse_spec(train_spec(stores["a"], [stores["b"]]))
    mapping = parse_spec(capped_spec(stores["a"], f'{{path: "{stores["b"]}"}}'))
    assert [e.path for e in plain.dataset.extra_train] == [str(stores["b"])]
    assert plain.dataset.extra_train[0].rows is None
    # a plain path (and {path} without rows) dumps as the plain path: keys of existing runs stay valid
    assert plain.section_dump(["dataset"])["dataset"]["extra_train"] == [str(stores["b"])]
    assert mapping.section_dump(["dataset"]) == plain.section_dump(["dataset"])
    capped = parse_spec(capped_spec(stores["a"], f'{{path: "{stores["b"]}", rows: 5}}'))
    assert capped.section_dump(["dataset"])["dataset"]["extra_train"] == [{"path": str(stores["b"]), "rows": 5}]

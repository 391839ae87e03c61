"""The hostile-input corpus (tests/hostile/): every spec, command line and broken store a careless or
hostile user can make ends in exit 2 and one line (no traceback), writes nothing anywhere, and leaves
existing data untouched. The CLI runs in-process; a handful of cases also as real subprocesses."""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from test_dataset_toy import SIM
from typer.testing import CliRunner

from invphys.cli import app

HERE = Path(__file__).resolve().parent
CORPUS = HERE / "hostile"
SPECS = sorted(CORPUS.glob("specs/*.yaml"))


def expectation(spec: Path) -> str:
    sidecar = spec.with_suffix(".expect")
    if sidecar.exists():
        return sidecar.read_text().strip()
    first = spec.read_bytes().split(b"\n", 1)[0].decode()
    assert first.startswith("# expect: "), spec
    return first[len("# expect: "):].strip()


def tree(root: Path) -> dict[str, str]:
    """Every file and folder under ``root`` with a hash of its content (folders: "dir")."""
    out = {}
    for p in sorted(root.rglob("*")):
        if p.is_symlink():
            out[str(p.relative_to(root))] = f"link to {os.readlink(p)}"
            continue
        out[str(p.relative_to(root))] = "dir" if p.is_dir() else hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def invoke(args: list[str]):
    return CliRunner().invoke(app, args)


def assert_one_line_error(result, expect: str, what: str) -> None:
    text = result.output.strip()
    assert result.exit_code == 2, f"{what}: exit {result.exit_code}: {text[:2000]}"
    assert "Traceback" not in text, what
    assert result.exception is None or isinstance(result.exception, SystemExit), f"{what}: {result.exception!r}"
    assert len(text.splitlines()) == 1, f"{what}: not one line:\n{text[:2000]}"
    assert text.startswith("error:") and expect in text, f"{what}: expected {expect!r} in {text!r}"


@pytest.fixture
def sandbox(tmp_path, monkeypatch):
    """A working directory holding an existing dataset (must stay untouched) and nothing else."""
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    monkeypatch.chdir(cwd)
    return cwd


def test_corpus_is_large_and_the_base_spec_is_valid(sandbox) -> None:
    assert len(SPECS) >= 100
    sys.path.insert(0, str(CORPUS))
    try:
        from make_corpus import BASE
    finally:
        sys.path.remove(str(CORPUS))
    (sandbox / "base.yaml").write_text(BASE)
    result = invoke(["validate", "base.yaml"])
    assert result.exit_code == 0, result.output


@pytest.mark.parametrize("spec", SPECS, ids=[p.stem for p in SPECS])
def test_hostile_spec(spec: Path, sandbox: Path) -> None:
    expect = expectation(spec)
    local = sandbox / "spec.yaml"
    shutil.copy(spec, local)
    before = tree(sandbox.parent)
    corpus_before = tree(CORPUS)
    for args in (["validate", "spec.yaml"], ["run", "spec.yaml", "--out", "out"],
                 ["dataset", "generate", "spec.yaml", "--out", "ds", "--no-progress"]):
        assert_one_line_error(invoke(args), expect, f"{spec.name}: invphys {' '.join(args)}")
    assert tree(sandbox.parent) == before, f"{spec.name}: something was written"
    assert tree(CORPUS) == corpus_before


# -- command lines -------------------------------------------------------------------------------------
GOOD = f"""\
name: ok
simulator: {{type: "{SIM}", n_frames: 10}}
dataset: {{n: 4, batch_size: 2}}
stages: [dataset]
"""

CLI_CASES = [
    (["validate", "missing.yaml"], "No such file"),
    (["validate", "adir"], "is a directory"),
    (["validate", "/dev/zero"], "not a regular file"),
    (["validate", "/dev/null"], "not a regular file"),
    (["run", "good.yaml", "--out", "afile"], "is a file"),
    (["run", "good.yaml", "--out", "out", "--stage", "datset"], "Did you mean 'dataset'"),
    (["run", "good.yaml", "--out", "out", "--force", "trian"], "Did you mean 'train'"),
    (["run", "adir", "--out", "out"], "is a directory"),
    (["dataset", "info", "nowhere"], "no invphys dataset"),
    (["dataset", "info", "afile"], "is a file"),
    (["dataset", "info", "adir"], "no invphys dataset"),
    (["dataset", "verify", "nowhere"], "no invphys dataset"),
    (["dataset", "generate", "good.yaml", "--out", "afile", "--no-progress"], "is a file"),
    (["dataset", "generate", "good.yaml", "--out", "adir", "--no-progress"], "not an invphys dataset"),
    (["dataset", "generate", "good.yaml", "--no-progress"], "no output directory"),
    (["dataset", "generate", "good.yaml", "--out", "ds", "--n", "10000000000", "--no-progress"], "must be <= 1000000"),
    (["simulate", "--simulator", SIM, "--params", '{"k": "abc"}', "--out", "sim"], "k = 'abc' is not a number"),
    (["simulate", "--simulator", SIM, "--params", '{"k": 1e9, "m": 0.1}', "--out", "sim"],
     "k = 1000000000 is outside its range [1, 10000] N/m; m = 0.1 is outside its range [0.5, 2] kg"),
    (["simulate", "--simulator", SIM, "--params", '{"c": 0.009999999}', "--out", "sim"], "c = 0.009999999 is outside"),
    (["simulate", "--simulator", SIM, "--params", '{"kk": 1}', "--out", "sim"], "Did you mean 'k'"),
    # issue 47: output places and paths that used to be internal errors (exit 1) or silently written into
    (["schema", "--out", "adir"], "'adir' is a directory"),
    (["schema", "--out", "afile/schema.json"], "lies under"),
    (["simulate", "--simulator", SIM, "--params", "adir", "--out", "sim"], "--params 'adir' is a directory"),
    (["run", "good.yaml", "--out", "afile/run"], "which is a file"),
    (["run", "good.yaml", "--out", "loop"], "symbolic-link loop"),
    (["run", "good.yaml", "--out", "loop/run"], "symbolic-link loop"),
    (["dataset", "generate", "good.yaml", "--out", "loop/ds", "--no-progress"], "symbolic-link loop"),
    (["dataset", "generate", "good.yaml", "--out", "afile/ds", "--no-progress"], "which is a file"),
    (["simulate", "--simulator", SIM, "--out", "loop/sim"], "symbolic-link loop"),
    (["validate", "good.yaml", "--out", "afile/run"], "which is a file"),
]


@pytest.mark.parametrize("args, expect", CLI_CASES, ids=[" ".join(a)[:60] for a, _ in CLI_CASES])
def test_hostile_command_line(args: list[str], expect: str, sandbox: Path) -> None:
    (sandbox / "good.yaml").write_text(GOOD)
    (sandbox / "afile").write_text("precious")
    (sandbox / "adir").mkdir()
    (sandbox / "adir" / "notes.txt").write_text("mine")
    (sandbox / "loop").symlink_to("loop")
    before = tree(sandbox)
    assert_one_line_error(invoke(args), expect, " ".join(args))
    assert tree(sandbox) == before


# -- nothing is written into a dataset store or an inverter bundle (issue 47) ----------------------------
BUNDLE_MANIFEST = "format_version: 2\ninvphys_version: 0.0\n"


@pytest.mark.parametrize("args, expect", [
    (["run", "good.yaml", "--out", "store/run"], "lies inside"),
    (["run", "good.yaml", "--out", "store"], "is a dataset store"),
    (["run", "good.yaml", "--out", "bundle/run"], "which is an inverter bundle"),
    (["run", "good.yaml", "--out", "bundle"], "is an inverter bundle"),
    (["run", "good.yaml", "--out", "link/run"], "a dataset store"),
    (["dataset", "generate", "good.yaml", "--out", "bundle/ds", "--no-progress"], "an inverter bundle"),
    (["dataset", "generate", "good.yaml", "--out", "store/inner", "--no-progress"], "a dataset store"),
    (["simulate", "--simulator", SIM, "--out", "store/sim"], "a dataset store"),
    (["validate", "good.yaml", "--out", "bundle/run"], "an inverter bundle"),
])
def test_outputs_inside_a_store_or_a_bundle_are_refused(args, expect, pristine_store, sandbox) -> None:
    shutil.copytree(pristine_store, sandbox / "store")
    (sandbox / "bundle").mkdir()
    (sandbox / "bundle" / "manifest.yaml").write_text(BUNDLE_MANIFEST)
    (sandbox / "link").symlink_to("store")
    (sandbox / "good.yaml").write_text(GOOD)
    before = tree(sandbox)
    assert_one_line_error(invoke(args), expect, " ".join(args))
    assert tree(sandbox) == before
    from invphys.core.dataset import DatasetStore

    assert DatasetStore(sandbox / "store").verify().ok


# -- broken stores: every reader refuses, nothing is changed ---------------------------------------------
def _break(kind: str, path: Path) -> None:
    parts = sorted(path.glob("part-*.parquet"))
    if kind == "deleted-part":
        parts[0].unlink()
    elif kind == "truncated-part":
        parts[0].write_bytes(parts[0].read_bytes()[:100])
    elif kind == "zeroed-part":
        parts[0].write_bytes(b"\0" * parts[0].stat().st_size)
    elif kind == "duplicated-part":
        shutil.copy(parts[0], path / "part-000123-0000beef.parquet")
    elif kind == "part-is-a-directory":
        (path / "part-000124-0000dead.parquet").mkdir()
    elif kind == "foreign-parquet":
        import pyarrow as pa
        import pyarrow.parquet as pq

        pq.write_table(pa.table({"x": [1, 2]}), path / "part-000125-0000f00d.parquet")
    elif kind.startswith("metadata-"):
        text = {"metadata-empty": "", "metadata-truncated": '{"format": "invphys-dat',
                "metadata-list": "[1, 2]", "metadata-types": '{"param_names": "k", "feature_names": [], "identity": 1}',
                "metadata-binary": "\x00\x01\x02"}[kind]
        (path / "_metadata.json").write_text(text)
    elif kind == "manifest-garbage":
        (path / "_manifest.json").write_text('{"parts": 7}')
    else:
        raise AssertionError(kind)


STORE_CASES = {
    "deleted-part": "missing", "truncated-part": "corrupt", "zeroed-part": "corrupt",
    "duplicated-part": "duplicate", "part-is-a-directory": "not a regular file", "foreign-parquet": "foreign",
    "metadata-empty": "not valid JSON", "metadata-truncated": "not valid JSON", "metadata-list": "not a JSON object",
    "metadata-types": "param_names", "metadata-binary": "not a text file", "manifest-garbage": "malformed",
}


@pytest.fixture(scope="module")
def pristine_store(tmp_path_factory) -> Path:
    from invphys.data.generate import generate_dataset

    path = tmp_path_factory.mktemp("hostile") / "store"
    generate_dataset(path, {"type": SIM, "n_frames": 10}, n=12, batch_size=4, seed=2, progress=False)
    return path


@pytest.mark.parametrize("kind", sorted(STORE_CASES))
def test_broken_store(kind: str, pristine_store: Path, sandbox: Path) -> None:
    store = sandbox / "store"
    shutil.copytree(pristine_store, store)
    _break(kind, store)
    (sandbox / "spec.yaml").write_text(GOOD.replace("dataset: {n: 4, batch_size: 2}", "dataset: {path: store}"))
    before = tree(sandbox)
    expect = STORE_CASES[kind]
    assert_one_line_error(invoke(["dataset", "info", "store"]), expect, f"{kind}: dataset info")
    assert_one_line_error(invoke(["dataset", "generate", "spec.yaml", "--out", "store", "--n", "16",
                                  "--no-progress"]), expect, f"{kind}: dataset generate")
    assert tree(sandbox) == before, f"{kind}: the broken store was changed"
    result = invoke(["run", "spec.yaml", "--out", "run"])
    assert_one_line_error(result, expect, f"{kind}: run")
    assert {k for k in tree(sandbox) if not k.startswith("run")} == set(before)


# -- a handful as real subprocesses --------------------------------------------------------------------
@pytest.mark.parametrize("name", ["alias-bomb", "nul-byte", "label-optimizer-01", "nonfinite-00", "reference-00",
                                  "validate-targets-unknown-feature", "validate-seed-huge-integer"])
def test_hostile_spec_in_a_real_subprocess(name: str, sandbox: Path) -> None:
    spec = next(p for p in SPECS if p.stem.endswith(name) and p.stem[3:] == "-" + name)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(HERE), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run([sys.executable, "-m", "invphys.cli", "run", str(spec), "--out", "out"],
                          capture_output=True, text=True, timeout=120, env=env, cwd=sandbox)
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert expectation(spec) in proc.stderr and proc.stdout == ""
    assert not any(sandbox.iterdir())

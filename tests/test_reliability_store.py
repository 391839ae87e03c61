"""Dataset integrity with real files: deleted, truncated, foreign and duplicated parts, a malformed
metadata file, a writer killed between writing a part and recording it; verify, repair, and readers
(ours, pandas, pyarrow.dataset) that never see a key twice; the run identity's config hash."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pandas as pd
import pyarrow.dataset as pads
import pyarrow.parquet as pq
import pytest
from test_dataset_toy import SIM, ToyOscillator
from typer.testing import CliRunner

from invphys.cli import app
from invphys.core.dataset import (
    MANIFEST_FILE,
    SCHEMA_KEY,
    DatasetError,
    DatasetStore,
    Row,
    RunIdentity,
    row_key,
)
from invphys.data.generate import generate_dataset

N, BATCH = 12, 4


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    path = tmp_path_factory.mktemp("store") / "ds"
    generate_dataset(path, {"type": SIM, "substeps": 1}, n=N, batch_size=BATCH, seed=1, progress=False)
    return path


@pytest.fixture
def store(pristine, tmp_path) -> DatasetStore:
    shutil.copytree(pristine, tmp_path / "ds")
    return DatasetStore(tmp_path / "ds")


def cli(*args: str):
    return CliRunner().invoke(app, list(args))


def one_line_error(result, *needles: str) -> str:
    text = result.output.strip()
    assert result.exit_code == 2, text
    assert "Traceback" not in text and len(text.splitlines()) == 1, text
    assert text.startswith("error:"), text
    for needle in needles:
        assert needle in text, text
    return text


def test_manifest_records_every_part_with_checksums_and_provenance(store) -> None:
    manifest = json.loads((store.path / MANIFEST_FILE).read_text())
    assert [p["rows"] for p in manifest["parts"]] == [BATCH] * (N // BATCH) and manifest["rows"] == N
    assert all(len(p["sha256"]) == 64 for p in manifest["parts"])
    part = store.path / manifest["parts"][0]["name"]
    prov = json.loads(pq.read_schema(part).metadata[SCHEMA_KEY])
    assert prov["identity"] == store.metadata["identity"] and prov["feature_names"] == list(store.feature_names)
    report = store.verify()
    assert report.ok and report.rows == N and report.parts == N // BATCH
    assert cli("dataset", "verify", str(store.path)).exit_code == 0


def test_deleted_part_is_named_then_repaired_then_regenerated(store) -> None:
    victim = store.parts()[1]
    victim.unlink()
    one_line_error(cli("dataset", "info", str(store.path)), "missing", victim.name, "--repair")
    with pytest.raises(DatasetError, match="missing"):
        store.arrays()
    bad = cli("dataset", "verify", str(store.path), "--json")
    # a damaged store is a finding, not a success (which non-zero code is the CLI's to document: issue 50)
    assert bad.exit_code != 0 and json.loads(bad.stdout)["problems"][0]["kind"] == "missing"
    fixed = cli("dataset", "verify", str(store.path), "--repair")
    assert fixed.exit_code == 0 and "dropped" in fixed.output
    assert len(store.arrays(ok_only=False)) == N - BATCH
    again = generate_dataset(store.path, {"type": SIM, "substeps": 1}, n=N, batch_size=BATCH, seed=1, progress=False)
    assert again.ran == BATCH and len(store.frame()) == N


def test_truncated_part_is_corrupt_and_quarantined(store) -> None:
    victim = store.parts()[0]
    victim.write_bytes(victim.read_bytes()[:200])
    one_line_error(cli("dataset", "info", str(store.path)), "corrupt", victim.name)
    report = store.repair()
    assert report.ok and (store.path / "_quarantine" / victim.name).is_file()
    assert len(pd.read_parquet(store.path)) == N - BATCH  # readers skip _quarantine/


def test_duplicated_part_is_refused_and_quarantined_so_no_reader_sees_twice(store) -> None:
    src = store.parts()[0]
    shutil.copy(src, store.path / "part-000099-deadbeef.parquet")
    one_line_error(cli("dataset", "info", str(store.path)), "duplicate", "part-000099-deadbeef.parquet")
    report = store.verify()
    assert [p.kind for p in report.problems] == ["duplicate"] and not report.ok
    store.repair()
    assert store.verify().ok
    for frame in (pd.read_parquet(store.path), pads.dataset(store.path).to_table().to_pandas(), store.frame()):
        assert len(frame) == N and frame["key"].is_unique


def test_renamed_copy_with_other_bytes_is_a_duplicate_by_keys(store) -> None:
    table = pq.read_table(store.parts()[0])
    pq.write_table(table, store.path / "part-000050-0badc0de.parquet", compression="snappy")
    problems = store.verify().problems
    assert [p.kind for p in problems] == ["duplicate"] and "row keys already stored" in problems[0].detail


def test_foreign_part_is_refused(store, tmp_path) -> None:
    other = tmp_path / "other"
    generate_dataset(other, {"type": SIM, "substeps": 2}, n=4, batch_size=4, seed=9, progress=False)
    shutil.copy(DatasetStore(other).parts()[0], store.path / "part-000077-12345678.parquet")
    one_line_error(cli("dataset", "info", str(store.path)), "foreign")
    pq.write_table(pq.read_table(store.parts()[0]).drop(["f_peak_abs"]), store.path / "part-000078-abcdef12.parquet")
    kinds = sorted(p.kind for p in store.verify().problems)
    assert kinds == ["foreign", "foreign"]


@pytest.mark.parametrize("text, needle", [
    ("{", "not valid JSON"), ("[]", "not a JSON object"), ('{"param_names": 5}', "param_names"),
    ('{"param_names": ["a"], "feature_names": ["f", "f"], "identity": {}}', "repeats"),
    ("\x00\x01binary", "not a text file"),
    ('{"param_names": ["a"],\n "param_names": ["b"]}', "'param_names' appears twice in one object (lines 1 and 2)"),
])
def test_malformed_metadata_is_one_line(store, text: str, needle: str) -> None:
    (store.path / "_metadata.json").write_text(text)
    one_line_error(cli("dataset", "info", str(store.path)), needle)


def test_malformed_manifest_and_a_file_for_a_store(store, tmp_path) -> None:
    (store.path / MANIFEST_FILE).write_text('{"parts": [{"name": "../../etc/passwd"}]}')
    one_line_error(cli("dataset", "info", str(store.path)), "malformed")
    report = store.repair()  # rebuilt from the parts; the bad name is never followed
    assert report.ok and "replaced the malformed manifest" in report.actions and len(store.frame()) == N
    (tmp_path / "afile").write_text("x")
    one_line_error(cli("dataset", "info", str(tmp_path / "afile")), "is a file")


def test_killed_between_part_and_manifest_is_adopted_on_resume(store) -> None:
    manifest = json.loads((store.path / MANIFEST_FILE).read_text())
    lost = manifest["parts"].pop()
    (store.path / MANIFEST_FILE).write_text(json.dumps(manifest))
    assert len(store.frame()) == N - BATCH  # readers read listed parts only
    assert [p.kind for p in store.verify().problems] == ["unlisted"]
    again = generate_dataset(store.path, {"type": SIM, "substeps": 1}, n=N, batch_size=BATCH, seed=1, progress=False)
    assert again.ran == 0 and store.verify().ok and len(store.frame()) == N
    assert lost["name"] in [p["name"] for p in json.loads((store.path / MANIFEST_FILE).read_text())["parts"]]


def test_a_key_is_never_stored_twice(store) -> None:
    df = store.frame()
    ident = RunIdentity(**store.metadata["identity"])
    theta = df.filter(like="theta_").to_numpy()[0]
    assert row_key(theta, ident) == df["key"][0]
    from invphys.core.results import RunStats, SimulationResult

    res = SimulationResult(params=theta, ok=False, stats=RunStats(), failure="x")
    with store.writer():
        store.create_or_check({k: store.metadata[k] for k in ("identity", "param_names", "feature_names")})
        with pytest.raises(DatasetError, match="twice"):
            store.append([Row(key=df["key"][0], sample_index=0, theta=theta, params=theta, result=res)])


def test_legacy_store_without_manifest_reads_and_repair_writes_one(store) -> None:
    (store.path / MANIFEST_FILE).unlink()
    assert len(store.frame()) == N
    report = store.verify()
    assert not report.ok and not report.has_manifest and not report.problems
    assert cli("dataset", "verify", str(store.path)).exit_code != 0
    assert store.repair().ok


def test_identity_hashes_the_whole_simulator_config(tmp_path) -> None:
    a, b = ToyOscillator(substeps=1), ToyOscillator(substeps=2)
    ia, ib = RunIdentity.of(a), RunIdentity.of(b)
    assert ia.config and ia.config != ib.config and ia.config == RunIdentity.of(ToyOscillator(substeps=1)).config
    theta = np.array([0.5, 0.5, 0.5])
    assert row_key(theta, ia) != row_key(theta, ib)
    # rows made with other settings are never reused: another setting is refused, not resumed
    path = tmp_path / "ds"
    generate_dataset(path, {"type": SIM, "substeps": 1}, n=4, batch_size=4, progress=False)
    with pytest.raises(DatasetError, match="identity"):
        generate_dataset(path, {"type": SIM, "substeps": 2}, n=4, batch_size=4, progress=False)
    # a store made before identities held the config: said plainly
    meta = json.loads((path / "_metadata.json").read_text())
    meta["identity"]["config"] = ""
    (path / "_metadata.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match="made before run identities included"):
        generate_dataset(path, {"type": SIM, "substeps": 1}, n=4, batch_size=4, progress=False)


def test_corrupt_store_in_a_real_subprocess(store) -> None:
    store.parts()[0].write_bytes(b"PAR1 not really")
    proc = subprocess.run([sys.executable, "-m", "invphys.cli", "dataset", "info", str(store.path)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert "corrupt" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1


# -- repair never follows links, never leaves the store; huge parts are never read whole -----------------
def tree_bytes(root) -> dict[str, bytes | str]:
    """Every entry under ``root`` (links not followed): a file's bytes, a link's target."""
    out: dict[str, bytes | str] = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = os.path.join(dirpath, name)
            rel = os.path.relpath(p, root)
            if os.path.islink(p):
                out[rel] = "-> " + os.readlink(p)
            elif os.path.isfile(p):
                out[rel] = open(p, "rb").read()
    return out


def test_repair_refuses_a_symlinked_quarantine_and_moves_nothing_out(store, tmp_path) -> None:
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    (store.path / "_quarantine").symlink_to(outside)
    victim = store.parts()[0]
    victim.write_bytes(b"\0" * victim.stat().st_size)
    before = tree_bytes(store.path)
    one_line_error(cli("dataset", "verify", str(store.path), "--repair"), "_quarantine", "symbolic link")
    from invphys.core.dataset import UnsafeStoreError

    with pytest.raises(UnsafeStoreError):
        store.repair()
    assert list(outside.iterdir()) == [] and tree_bytes(store.path) == before


def test_a_symlinked_part_is_never_read_and_repair_moves_only_the_link(store, tmp_path) -> None:
    # a listed part moved out of the store and linked back in: readers must not follow it
    outside = tmp_path / "outside.parquet"
    victim = store.parts()[1]
    victim.rename(outside)
    victim.symlink_to(outside)
    kept = outside.read_bytes()
    problems = store.verify().problems
    assert [(p.part, p.kind) for p in problems] == [(victim.name, "corrupt")], problems
    assert "symbolic link" in problems[0].detail
    one_line_error(cli("dataset", "info", str(store.path)), victim.name, "symbolic link")
    report = store.repair()
    moved = store.path / "_quarantine" / victim.name
    assert report.ok and moved.is_symlink() and not victim.exists()
    assert outside.read_bytes() == kept and len(store.frame()) == N - BATCH


@contextlib.contextmanager
def unwritable(path):
    """``path`` made unwritable even for root (an immutable directory when running as root)."""
    if os.geteuid() == 0:
        if subprocess.run(["chattr", "+i", str(path)], capture_output=True).returncode != 0:
            pytest.skip("running as root without chattr: cannot make a read-only directory")
        undo = ["chattr", "-i", str(path)]
    else:
        os.chmod(path, 0o555)
        undo = ["chmod", "755", str(path)]
    try:
        yield path
    finally:
        subprocess.run(undo, check=True)


@pytest.mark.parametrize("with_lock_file", [True, False])
def test_repair_of_a_read_only_store_is_one_line_and_changes_nothing(store, with_lock_file) -> None:
    victim = store.parts()[0]
    victim.write_bytes(victim.read_bytes()[:300])
    lock = store.path / ".lock"
    if with_lock_file:
        lock.touch()
    else:
        lock.unlink(missing_ok=True)
    before = tree_bytes(store.path)
    with unwritable(store.path):
        one_line_error(cli("dataset", "verify", str(store.path), "--repair"), "cannot change", "nothing was changed")
        assert tree_bytes(store.path) == before
        assert not store.verify().ok  # reading a read-only store still works
    assert tree_bytes(store.path) == before


def test_a_huge_stray_part_is_refused_without_being_read(store) -> None:
    """A 4 GB sparse file among the parts, and a listed part grown to 4 GB: verified in a process that
    cannot hold 1 GB (reading either whole fails with MemoryError there)."""
    stray = store.path / "part-000099-deadbeef.parquet"
    with open(stray, "wb") as fh:
        fh.truncate(4 << 30)
    grown = store.parts()[0]
    with open(grown, "r+b") as fh:
        fh.truncate(4 << 30)
    code = ("import resource, json, sys; resource.setrlimit(resource.RLIMIT_AS, (800 << 20, 800 << 20));"
            "from invphys.core.dataset import DatasetStore;"
            "print(json.dumps(DatasetStore(sys.argv[1]).verify().to_dict()))")
    proc = subprocess.run([sys.executable, "-c", code, str(store.path)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    problems = {p["part"]: p for p in json.loads(proc.stdout)["problems"]}
    assert set(problems) == {stray.name, grown.name}
    assert problems[stray.name]["kind"] == "corrupt" and "not read" in problems[stray.name]["detail"]
    assert problems[grown.name]["kind"] == "corrupt" and "manifest says" in problems[grown.name]["detail"]
    assert len(store.repair().actions) == 2 and store.verify().ok and len(store.frame()) == N - BATCH


def test_stray_files_that_are_not_parquet_are_not_read_and_parts_respect_the_size_limit(store, monkeypatch) -> None:
    stray = store.path / "part-000098-cafebabe.parquet"
    stray.write_bytes(b"x" * 5000)
    (problem,) = store.verify().problems
    assert problem.part == stray.name and "do not start and end like a Parquet file" in problem.detail
    stray.unlink()
    # a writer never makes a part its readers would refuse: a batch over the limit is split
    monkeypatch.setenv("INVPHYS_MAX_PART_BYTES", "9000")
    limited = store.path.parent / "limited"
    generate_dataset(limited, {"type": SIM, "substeps": 1}, n=N, batch_size=N, seed=1, progress=False)
    parts = DatasetStore(limited).parts()
    assert len(parts) > 1 and all(p.stat().st_size <= 9000 for p in parts)
    assert DatasetStore(limited).verify().ok and len(DatasetStore(limited).frame()) == N
    monkeypatch.setenv("INVPHYS_MAX_PART_BYTES", "1000")
    (problem, *_) = DatasetStore(limited).verify().problems
    assert problem.kind == "corrupt" and "INVPHYS_MAX_PART_BYTES" in problem.detail


def test_entries_that_are_not_parts_are_reported_never_read_nor_moved(store) -> None:
    """What another program wrote into the store (a run directory, notes) breaks pandas.read_parquet(DIR):
    verify says so; invphys's own readers are unaffected and repair moves none of it."""
    (store.path / "run").mkdir()
    (store.path / "run" / "summary.json").write_text("{}")
    (store.path / "notes.txt").write_text("mine")
    with pytest.raises(ValueError):   # pyarrow: ArrowInvalid
        pd.read_parquet(store.path)
    report = store.verify()
    assert not report.ok and sorted((p.part, p.kind) for p in report.problems) == [("notes.txt", "stray"),
                                                                                   ("run", "stray")]
    assert len(store.frame()) == N  # invphys readers read parts only
    repaired = store.repair()
    assert not repaired.ok and all("left" in a for a in repaired.actions) and len(repaired.actions) == 2
    assert (store.path / "notes.txt").read_text() == "mine" and (store.path / "run" / "summary.json").is_file()
    assert not (store.path / "_quarantine").exists()


def test_verify_reports_a_malformed_manifest_as_damage_instead_of_raising(store) -> None:
    (store.path / MANIFEST_FILE).write_text('{"parts": 7}')
    report = store.verify()   # before: DatasetError, so `dataset verify` could only say it as an error
    assert not report.ok and [(p.part, p.kind) for p in report.problems] == [(MANIFEST_FILE, "corrupt")]
    assert "malformed" in report.problems[0].detail and report.rows == N
    out = cli("dataset", "verify", str(store.path), "--json")
    assert out.exit_code != 0 and json.loads(out.stdout)["problems"][0]["part"] == MANIFEST_FILE
    assert store.repair().ok and store.verify().ok


def test_a_stray_part_far_larger_than_the_listed_ones_is_not_read(store) -> None:
    """100 MB that start and end like Parquet, named like a part the manifest does not list (sparse: no
    disk); a killed writer's part is about as large as the others, so this one is reported unread."""
    stray = store.path / "part-000097-abcdefab.parquet"
    with open(stray, "wb") as fh:
        fh.write(b"PAR1")
        fh.seek(100 << 20)
        fh.write(b"PAR1")
    (problem,) = store.verify().problems
    assert problem.part == stray.name and problem.kind == "corrupt"
    assert "far more than any part the manifest lists" in problem.detail and "not read" in problem.detail

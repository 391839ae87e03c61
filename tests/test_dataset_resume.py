"""Crash safety end to end: `invphys dataset generate` killed with SIGKILL, then resumed; time limits;
the CLI's info output; and the dataset stage of `invphys run`."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from test_dataset_toy import SIM, ToyOscillator
from typer.testing import CliRunner

from invphys.cli import app
from invphys.core.dataset import DatasetStore, RunIdentity, round_theta, row_keys
from invphys.core.sampling import sample_unit
from invphys.data.generate import generate_dataset

TESTS = str(Path(__file__).resolve().parent)
N = 48

SPEC = f"""\
name: kill-test
seed: 3
stages: [dataset]
simulator: {{type: "{SIM}", substeps: 1, raise_c_above: 0.7, sleep_s: 0.06}}
executor: {{type: local}}
dataset: {{n: {N}, batch_size: 4, sampler: sobol}}
"""


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": os.pathsep.join([TESTS, os.environ.get("PYTHONPATH", "")]),
            "INVPHYS_DISABLE_PLUGIN_AUTOLOAD": "1"}


def _generate(spec: Path, out: Path, *extra: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "invphys.cli", "dataset", "generate", str(spec), "--out",
                             str(out), "--no-progress", "--json", *extra], env=_env(), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def test_sigkill_mid_run_then_resume_stores_every_row_exactly_once(tmp_path) -> None:
    spec, out = tmp_path / "spec.yaml", tmp_path / "ds"
    spec.write_text(SPEC)
    proc = _generate(spec, out)
    deadline = time.monotonic() + 60
    while len(list(out.glob("part-*.parquet"))) < 3:  # the first flush writes no part: wait for 2 batches
        assert proc.poll() is None, proc.stderr.read()
        assert time.monotonic() < deadline, "no parts appeared"
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=10)
    assert proc.returncode == -signal.SIGKILL
    partial = pd.read_parquet(out)
    assert 0 < len(partial) < N and partial["key"].is_unique

    done = _generate(spec, out)
    stdout, stderr = done.communicate(timeout=120)
    assert done.returncode == 0, stderr
    summary = json.loads(stdout)
    assert summary["already_present"] == len(partial) and summary["ran"] == N - len(partial)
    assert summary["complete"] and summary["total_rows"] == N

    df = pd.read_parquet(out)
    sim = ToyOscillator(substeps=1, raise_c_above=0.7, sleep_s=0.06)
    space = sim.parameter_space()
    expected = row_keys(round_theta(sample_unit(N, space.dim, "sobol", 3)), RunIdentity.of(sim))
    assert len(df) == N and sorted(df["key"]) == sorted(expected)  # every row exactly once
    failed = df[df["status"] == "failed"]
    assert failed["failure"].str.startswith("RuntimeError: toy oscillator exploded").any()
    assert failed["failure"].str.startswith("blow-up").any()
    assert failed["f_peak_abs"].isna().all() and df.loc[df["status"] == "ok", "f_peak_abs"].notna().all()
    meta = DatasetStore(out).metadata
    assert [s.get("stop_reason") for s in meta["sessions"]][-1] == "complete"
    assert meta["spec"]["name"] == "kill-test" and meta["totals"]["rows"] == N

    # an uninterrupted run stores the same rows with the same features (resuming changes nothing)
    ref = tmp_path / "ref"
    generate_dataset(ref, {"type": SIM, "substeps": 1, "raise_c_above": 0.7, "sleep_s": 0.06}, n=N, batch_size=4,
                     sampler="sobol", seed=3, progress=False)
    a, b = DatasetStore(out).arrays(ok_only=False), DatasetStore(ref).arrays(ok_only=False)
    assert a.fingerprint == b.fingerprint
    np.testing.assert_array_equal(a.ok, b.ok)
    np.testing.assert_array_equal(a.y, b.y)


def test_limit_minutes_stops_cleanly_and_sigterm_keeps_rows(tmp_path) -> None:
    path = tmp_path / "ds"
    sim = {"type": SIM, "sleep_s": 0.05}
    t0 = time.monotonic()
    s = generate_dataset(path, sim, n=200, batch_size=4, limit_minutes=0.01, progress=False)  # 0.6 s
    assert time.monotonic() - t0 < 5
    assert s.stop_reason == "time_limit" and not s.complete and 0 < s.ran < 200
    assert len(pd.read_parquet(path)) == s.ran  # nothing computed is lost
    assert DatasetStore(path).metadata["sessions"][-1]["stop_reason"] == "time_limit"

    spec = tmp_path / "spec.yaml"
    spec.write_text(SPEC)
    proc = _generate(spec, tmp_path / "term")
    deadline = time.monotonic() + 60
    while len(list((tmp_path / "term").glob("part-*.parquet"))) < 2:
        assert proc.poll() is None and time.monotonic() < deadline
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    stdout, _ = proc.communicate(timeout=30)
    assert proc.returncode == 143, stdout
    summary = json.loads(stdout)
    assert summary["stop_reason"] == "terminated"
    assert len(pd.read_parquet(tmp_path / "term")) == summary["ran"] > 0


def test_cli_info_json_and_bad_input(tmp_path) -> None:
    path = tmp_path / "ds"
    generate_dataset(path, {"type": SIM, "substeps": 1}, n=24, batch_size=8, progress=False)
    runner = CliRunner()
    res = runner.invoke(app, ["dataset", "info", str(path), "--json"])
    assert res.exit_code == 0, res.output
    info = json.loads(res.stdout)
    df = pd.read_parquet(path)
    assert info["rows"] == 24 and info["ok"] == int((df["status"] == "ok").sum()) and info["failed"] > 0
    assert sum(info["failures_by_reason"].values()) == info["failed"]
    ok = df.loc[df["status"] == "ok", "f_peak_abs"]
    assert info["features"]["peak_abs"]["p50"] == pytest.approx(float(np.percentile(ok, 50)))
    assert info["identity"]["simulator"] == "toy_oscillator" and info["devices"] == ["cpu"]
    res = runner.invoke(app, ["dataset", "info", str(tmp_path / "nope")])
    assert res.exit_code == 2 and "no invphys dataset" in res.output


def test_dataset_stage_generates_then_is_cached(tmp_path) -> None:
    from invphys.core.spec import parse_spec
    from invphys.pipeline.runner import run_spec

    spec = parse_spec(SPEC.replace("sleep_s: 0.06", "sleep_s: 0").replace(f"n: {N}", "n: 20"))
    first = run_spec(spec, tmp_path / "run", progress=False)
    assert first["dataset"]["ran"] == 20 and first["dataset"]["total_rows"] == 20
    store = DatasetStore(tmp_path / "run" / "dataset" / "store")
    assert len(store.frame()) == 20
    assert first["dataset"]["fingerprint"] == store.arrays().fingerprint
    messages = []
    run_spec(spec, tmp_path / "run", progress=False, on_stage=lambda s, status, _: messages.append(status))
    assert messages == ["cached"]


def test_dataset_stage_stopped_by_its_time_limit_is_not_marked_done(tmp_path) -> None:
    from invphys.core.spec import parse_spec
    from invphys.pipeline.runner import run_spec
    from invphys.pipeline.stages.dataset import DatasetIncomplete

    text = SPEC.replace("sleep_s: 0.06", "sleep_s: 0.05").replace("sampler: sobol", "limit_minutes: 0.005")
    spec = parse_spec(text)
    with pytest.raises(DatasetIncomplete, match="run again to resume"):
        run_spec(spec, tmp_path / "run", progress=False)
    assert not (tmp_path / "run" / "dataset" / "DONE.json").exists()
    stored = len(pd.read_parquet(tmp_path / "run" / "dataset" / "store"))
    assert 0 < stored < N
    done = run_spec(parse_spec(text.replace("limit_minutes: 0.005", "limit_minutes: 5")), tmp_path / "run",
                    progress=False)
    assert done["dataset"]["already_present"] == stored and done["dataset"]["total_rows"] == N

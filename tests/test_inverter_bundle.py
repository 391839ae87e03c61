"""Inverter bundles: written by the train/invert stages, loaded with checks, exported by the CLI."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import yaml
from test_inverter_support import toy_run
from typer.testing import CliRunner


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    return toy_run(tmp_path_factory.getbasetemp())


@pytest.fixture
def bundle_copy(run, tmp_path):
    dst = tmp_path / "bundle"
    shutil.copytree(run / "inverter", dst)
    return dst


def _edit_manifest(root, change) -> None:
    path = root / "manifest.yaml"
    data = yaml.safe_load(path.read_text())
    change(data)
    path.write_text(yaml.safe_dump(data, sort_keys=False))


def test_stages_write_a_complete_bundle(run) -> None:
    from invphys.inverter import load_inverter

    root = run / "inverter"
    m = yaml.safe_load((root / "manifest.yaml").read_text())
    assert m["format_version"] == 2 and m["simulator"]["version"] == "1"
    assert m["parameter_space"]["names"] == ["k", "c", "m"]
    assert m["parameter_space"]["units"] == ["N/m", "N s/m", "kg"]
    assert m["features"]["names"] == ["peak_abs", "final_abs", "log_decay", "crossings_per_s", "final_damage"]
    assert set(m["methods"]) == {"cma", "gc", "gc_flow", "ws"}
    assert m["methods"]["gc"]["kind"] == "policy" and m["methods"]["cma"]["kind"] == "optimizer"
    assert m["default_method"] in ("gc", "gc_flow")  # the best amortised policy on held-out targets
    best = max(("gc", "gc_flow"), key=lambda k: m["methods"][k]["heldout"]["mean_r_surrogate"])
    assert m["default_method"] == best
    assert m["dataset"]["n_train"] + m["dataset"]["n_test"] == m["dataset"]["n_rows"]
    # every part is hashed, and every network has a verified NumPy form
    assert all((root / p).is_file() for p in m["files"])
    assert m["components"]["surrogate"]["inference"]
    assert all(e["decoder"] for e in m["components"]["latents"].values())
    assert all(m["methods"][k]["inference"] for k in ("gc", "gc_flow"))
    inv = load_inverter(root)
    assert inv.notes == [] and inv.parameter_names == ("k", "c", "m")


def test_a_written_bundle_holds_no_pickle(run) -> None:
    """Format 2: policies as tensors (policy.npz), no SB3 zip; every weight file passes the pickle scan."""
    from invphys.inverter.manifest import pickle_problem

    root = run / "inverter"
    files = yaml.safe_load((root / "manifest.yaml").read_text())["files"]
    assert {"policies/gc/policy.npz", "policies/gc/gc_ppo.json"} <= set(files)
    assert not [f for f in files if f.endswith((".zip", ".pkl", ".pickle", "npe.pt"))]
    assert all(pickle_problem(root / f) is None for f in files)
    assert sorted(p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file()) == \
        sorted([*files, "manifest.yaml"])  # nothing in the bundle escapes the checksums


def test_bundle_policies_answer_exactly_like_the_invert_stage(run) -> None:
    from invphys.inverter import load_inverter

    inv = load_inverter(run / "inverter")
    rows = json.loads((run / "invert" / "results.json").read_text())
    targets = np.array(json.loads((run / "invert" / "targets.json").read_text())["features"])
    for label in ("gc", "gc_flow"):
        mine = [r for r in rows if r["optimizer"] == label]
        theta = inv.invert_array(targets[[r["target_index"] for r in mine]], method=label)
        np.testing.assert_allclose(theta, [r["theta"] for r in mine], atol=1e-5)
        res = inv.invert(targets[mine[0]["target_index"]], method=label)
        assert res.r_surrogate == pytest.approx(mine[0]["r_surrogate"], abs=1e-4)


def test_numpy_forms_match_the_plugins(run) -> None:
    from invphys.inverter.bundle import Bundle

    b = Bundle(run / "inverter")
    theta = np.random.default_rng(1).uniform(0, 1, (50, 3))
    mean, std = b.surrogate.predict_with_uncertainty(theta)
    ref_mean, ref_std = b.surrogate_model().predict_with_uncertainty(theta)
    np.testing.assert_allclose(mean, ref_mean, rtol=1e-4, atol=1e-4 * np.abs(ref_mean).max())
    np.testing.assert_allclose(std, ref_std, rtol=1e-3, atol=1e-4 * np.abs(ref_mean).max())
    assert std.max() > 0  # an ensemble: the std is real
    z = np.random.default_rng(2).uniform(-3, 3, (50, 2))
    for label in ("flow", "vae"):
        np.testing.assert_allclose(b.latent(label).decode(z), b.latent_model(label).decode(z), atol=1e-4)


def test_missing_or_changed_parts_fail_clearly(bundle_copy) -> None:
    from invphys.inverter import BundleError, load_inverter

    (bundle_copy / "surrogate" / "weights.pt").write_bytes(b"tampered")
    with pytest.raises(BundleError, match=r"surrogate/weights.pt has changed"):
        load_inverter(bundle_copy)
    (bundle_copy / "surrogate" / "weights.pt").unlink()
    with pytest.raises(BundleError, match=r"missing part surrogate/weights.pt"):
        load_inverter(bundle_copy)
    (bundle_copy / "manifest.yaml").unlink()
    with pytest.raises(BundleError, match="not an inverter bundle"):
        load_inverter(bundle_copy)
    with pytest.raises(BundleError, match="no such directory"):
        load_inverter(bundle_copy / "nope")


def test_run_directory_hint(run) -> None:
    from invphys.inverter import BundleError, load_inverter

    with pytest.raises(BundleError, match=r"its bundle is in inverter/"):
        load_inverter(run)


def test_newer_format_asks_to_upgrade(bundle_copy) -> None:
    from invphys.inverter import BundleError, load_inverter

    _edit_manifest(bundle_copy, lambda m: m.update(format_version=99, invphys_version="9.0"))
    with pytest.raises(BundleError, match="upgrade invphys"):
        load_inverter(bundle_copy)


def test_other_simulator_version_or_features_fail_unless_allowed(bundle_copy) -> None:
    from invphys.inverter import BundleError, load_inverter

    _edit_manifest(bundle_copy, lambda m: m["simulator"].update(version="0"))
    with pytest.raises(BundleError, match=r"trained on simulator .* 0, the installed one is 1"):
        load_inverter(bundle_copy)
    inv = load_inverter(bundle_copy, strict=False)
    assert any("retrain" in n for n in inv.notes)
    _edit_manifest(bundle_copy, lambda m: (m["simulator"].update(version="1"),
                                           m["features"]["names"].__setitem__(0, "peak")))
    with pytest.raises(BundleError, match=r"other features .*new: peak_abs; gone: peak"):
        load_inverter(bundle_copy)


def test_export_copies_a_loadable_bundle(run, tmp_path) -> None:
    from invphys.cli import app
    from invphys.inverter import load_inverter

    runner = CliRunner()
    out = tmp_path / "shipped"
    res = runner.invoke(app, ["export", str(run), "--out", str(out), "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["default_method"] == load_inverter(out).default_method
    again = runner.invoke(app, ["export", str(run), "--out", str(out)])
    assert again.exit_code == 2 and "--force" in again.output
    assert runner.invoke(app, ["export", str(run), "--out", str(out), "--force"]).exit_code == 0
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    res = runner.invoke(app, ["export", str(run), "--out", str(other), "--force"])
    assert res.exit_code == 2 and (other / "notes.txt").read_text() == "mine"
    res = runner.invoke(app, ["export", str(tmp_path / "no-run"), "--out", str(tmp_path / "x")])
    assert res.exit_code == 2 and "no such directory" in res.output
    # the copy holds exactly the source's listed files (a stray file in the source does not travel)
    stray = tmp_path / "src"
    shutil.copytree(run / "inverter", stray)
    (stray / "notes.txt").write_text("not part of the bundle")
    assert runner.invoke(app, ["export", str(stray), "--out", str(out), "--force"]).exit_code == 0
    assert not (out / "notes.txt").exists() and load_inverter(out).default_method
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no temporary sibling left


def test_answering_imports_no_torch(run) -> None:
    import os
    import subprocess
    import sys

    probe = ("import sys, invphys\n"
             f"inv = invphys.load_inverter({str(run / 'inverter')!r})\n"
             "_, y = inv.bundle.data('test')\n"
             "inv.invert(y[0]); inv.invert_many(y[:40]); inv.invert_array(y[:40])\n"
             "print(sorted(m for m in ('torch', 'stable_baselines3', 'zuko') if m in sys.modules))")
    tests = os.path.dirname(os.path.abspath(__file__))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([tests, os.environ.get("PYTHONPATH", "")])}
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().splitlines()[-1] == "[]"

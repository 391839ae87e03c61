"""What loading or exporting a bundle someone handed us may do: never run code stored in it, never read
outside it, never destroy data. Each class of hostile or careless bundle gets exit 2 and one ``error:``
line naming the file (checked through real ``invphys`` processes where the exit status matters)."""

from __future__ import annotations

import hashlib
import json
import os
import pickle
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from test_inverter_support import toy_run


class _Exec:
    """Pickles to a call of ``exec`` that writes ``marker``: proof that loading ran code."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return exec, (f"open({str(self.marker)!r}, 'w').write('ran')",)


@pytest.fixture(scope="module")
def toy(tmp_path_factory) -> Path:
    """The toy run's bundle plus a fitted NPE method (policies/npe), so every kind of weight file is there."""
    from invphys.inverter.bundle import Bundle
    from invphys.plugins.baselines import NPEBaseline

    src = toy_run(tmp_path_factory.getbasetemp()) / "inverter"
    root = tmp_path_factory.mktemp("safety") / "toy"
    shutil.copytree(src, root)
    b = Bundle(root)
    theta, y = b.data("train")
    npe = NPEBaseline(estimator="mdn", hidden_features=8, max_num_epochs=2, samples=8)
    npe.fit(theta, y, b.scales)
    npe.save(root / "policies" / "npe")
    manifest = yaml.safe_load((root / "manifest.yaml").read_text())
    manifest["methods"]["npe"] = {"type": "npe", "kind": "policy", "space": "raw", "evaluator": "shared",
                                  "config": {"estimator": "mdn", "hidden_features": 8, "samples": 8},
                                  "path": "policies/npe"}
    _write(root, manifest)
    return root


@pytest.fixture
def bundle(toy, tmp_path) -> Path:
    dst = tmp_path / "bundle"
    shutil.copytree(toy, dst)
    return dst


@pytest.fixture(scope="module")
def target_file(toy, tmp_path_factory) -> Path:
    from invphys.inverter.bundle import Bundle

    b = Bundle(toy)
    path = tmp_path_factory.mktemp("targets") / "targets.json"
    path.write_text(json.dumps([dict(zip(b.feature_names, map(float, b.data("test")[1][0]), strict=True))]))
    return path


def _write(root: Path, manifest: dict) -> None:
    """Write ``manifest`` with every file's checksum recomputed (as whoever edits a bundle can)."""
    files = {}
    for p in sorted(root.rglob("*")):
        if p.is_file() and not p.is_symlink() and p.name != "manifest.yaml":
            files[p.relative_to(root).as_posix()] = hashlib.sha256(p.read_bytes()).hexdigest()
    manifest["files"] = files
    (root / "manifest.yaml").write_text(yaml.safe_dump(manifest, sort_keys=False))


def _edit(root: Path, change) -> None:
    manifest = yaml.safe_load((root / "manifest.yaml").read_text())
    change(manifest)
    _write(root, manifest)


def _rehash(root: Path) -> None:
    _edit(root, lambda m: None)


def invphys(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", "from invphys.cli import main; main()", *map(str, args)],
                          capture_output=True, text=True, timeout=300)


def one_error(res: subprocess.CompletedProcess, *needles: str) -> str:
    """The single ``error:`` line of a run that exited 2 with no traceback; it contains every needle."""
    assert res.returncode == 2, (res.returncode, res.stdout, res.stderr)
    assert "Traceback" not in res.stderr
    errors = [ln for ln in res.stderr.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1, res.stderr
    for needle in needles:
        assert needle in errors[0], errors[0]
    return errors[0]


def snapshot(root: Path) -> dict[str, bytes | str]:
    """Every file's bytes and every link's target under ``root`` (what a data-loss check compares)."""
    out: dict[str, bytes | str] = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            rel = p.relative_to(root).as_posix()
            if p.is_symlink():
                out[rel] = "-> " + os.readlink(p)
            elif p.is_file():
                out[rel] = p.read_bytes()
            else:
                out[rel] = "dir"
    return out


# -- 1. no code runs ------------------------------------------------------------------------------------
def _torch_pickle(path: Path, marker: Path) -> None:
    import torch

    torch.save({"weight": _Exec(marker)}, path)


def _torch_pickle_protocol4(path: Path, marker: Path) -> None:
    import torch

    torch.save({"weight": _Exec(marker)}, path, pickle_protocol=4)


def _raw_pickle(path: Path, marker: Path) -> None:
    path.write_bytes(pickle.dumps({"w": _Exec(marker)}))


def _object_array(path: Path, marker: Path) -> None:
    with path.open("wb") as fh:
        np.savez(fh, w=np.array([_Exec(marker)], dtype=object))


PLANTED = [("surrogate/weights.pt", _torch_pickle), ("latents/flow/weights.pt", _torch_pickle_protocol4),
           ("latents/vae/weights.pt", _raw_pickle), ("inference/surrogate.npz", _raw_pickle),
           ("inference/policy_gc.npz", _object_array), ("policies/gc/policy.npz", _object_array),
           ("policies/npe/npe_weights.npz", _raw_pickle), ("data/train.npz", _object_array)]


@pytest.mark.parametrize("rel,plant", PLANTED, ids=[p for p, _ in PLANTED])
def test_a_planted_pickle_in_any_weight_file_is_refused_and_never_runs(bundle, rel, plant, tmp_path) -> None:
    from invphys.inverter import BundleError, load_inverter

    marker = tmp_path / "ran.txt"
    plant(bundle / rel, marker)
    _rehash(bundle)  # the checksum is no defence: whoever plants the file edits the manifest too
    with pytest.raises(BundleError, match=rf"{rel} (holds|is not a)"):
        load_inverter(bundle)
    assert not marker.exists()


def test_the_loaders_themselves_refuse_pickles_that_the_scan_would_miss(tmp_path) -> None:
    """Behind the scan: torch weights load with weights_only=True, NumPy weights with allow_pickle=False."""
    from invphys.models.base import load_torch_weights, read_weights_npz
    from invphys.models.data import ModelLoadError

    marker = tmp_path / "ran.txt"
    _torch_pickle(tmp_path / "w.pt", marker)
    with pytest.raises(ModelLoadError, match=r"w\.pt: not a weights file invphys loads without running code"):
        load_torch_weights(tmp_path / "w.pt")
    _object_array(tmp_path / "w.npz", marker)
    with pytest.raises(ModelLoadError, match=r"w\.npz: not a weights archive invphys loads without running code"):
        read_weights_npz(tmp_path / "w.npz")
    assert not marker.exists()


def test_planted_pickle_through_the_cli_is_one_error_line(bundle, target_file, tmp_path) -> None:
    marker = tmp_path / "ran.txt"
    _torch_pickle(bundle / "surrogate" / "weights.pt", marker)
    _rehash(bundle)
    one_error(invphys("invert", bundle, "--target", target_file, "--json"), "surrogate/weights.pt", "pickled code")
    assert not marker.exists()


# -- 2. nothing outside the bundle is read ----------------------------------------------------------------
def _outside(bundle: Path) -> Path:
    other = bundle.parent / "elsewhere"
    shutil.copytree(bundle / "surrogate", other)
    return other


ESCAPES = {
    "dotdot": lambda b: _edit(b, lambda m: m["components"]["surrogate"].update(path=f"../{_outside(b).name}")),
    "absolute": lambda b: _edit(b, lambda m: m["components"]["surrogate"].update(path=str(_outside(b)))),
    "policy_dotdot": lambda b: _edit(b, lambda m: m["methods"]["gc"].update(path="policies/../../elsewhere")),
    "files_dotdot": lambda b: _edit(b, lambda m: None) or _add_file_entry(b, "../elsewhere/weights.pt"),
}


def _add_file_entry(root: Path, rel: str) -> None:
    manifest = yaml.safe_load((root / "manifest.yaml").read_text())
    manifest["files"][rel] = "0" * 64
    (root / "manifest.yaml").write_text(yaml.safe_dump(manifest, sort_keys=False))


@pytest.mark.parametrize("how", sorted(ESCAPES))
def test_paths_leaving_the_bundle_are_refused(bundle, how) -> None:
    from invphys.inverter import BundleError, load_inverter

    _outside(bundle) if how.startswith(("policy", "files")) else None
    ESCAPES[how](bundle)
    with pytest.raises(BundleError, match="points outside the bundle"):
        load_inverter(bundle)


def test_a_symlink_leaving_the_bundle_is_refused_through_the_cli(bundle, target_file) -> None:
    other = _outside(bundle)
    shutil.rmtree(bundle / "surrogate")
    (bundle / "surrogate").symlink_to(other, target_is_directory=True)
    # the checksums still match (the files are copies): only the path gives it away
    one_error(invphys("invert", bundle, "--target", target_file), "leads outside the bundle through a symlink")


def test_an_unlisted_file_in_a_component_is_refused(bundle) -> None:
    from invphys.inverter import BundleError, load_inverter

    shutil.copy(bundle / "surrogate" / "weights.pt", bundle / "surrogate" / "extra.pt")
    with pytest.raises(BundleError, match=r"surrogate/extra\.pt is not listed in the manifest's files"):
        load_inverter(bundle)


# -- 3. wrong shapes and missing keys: one line naming the part or key ---------------------------------------
def _shrink_first_matrix(path: Path) -> str:
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    key = next(k for k, v in arrays.items() if v.ndim >= 2)
    arrays[key] = arrays[key][..., :-1]
    with path.open("wb") as fh:
        np.savez(fh, **arrays)
    return key


def test_a_surrogate_form_of_the_wrong_shape_names_the_part(bundle, target_file) -> None:
    _shrink_first_matrix(bundle / "inference" / "surrogate.npz")
    _rehash(bundle)
    one_error(invphys("invert", bundle, "--target", target_file), "inference/surrogate.npz",
              "the surrogate's NumPy form", "does not fit the bundle")


@pytest.mark.parametrize("rel,what", [("inference/policy_gc.npz", "the actor of policy 'gc'"),
                                      ("inference/latent_vae_decoder.npz", "the decoder of latent model 'vae'")])
def test_policy_and_decoder_forms_of_the_wrong_shape_name_the_part(bundle, rel, what) -> None:
    from invphys.inverter import BundleError, load_inverter

    _shrink_first_matrix(bundle / rel)
    _rehash(bundle)
    inv = load_inverter(bundle)
    method, space = ("gc", None) if "policy" in rel else (None, "vae")
    with pytest.raises(BundleError, match=rf"{rel} \({what}\) does not fit the bundle"):
        if method:
            inv.invert_array(inv.bundle.data("test")[1][:2], method=method)
        else:
            inv.bundle.latent(space)


def test_torch_weights_of_the_wrong_shape_name_the_tensor(bundle) -> None:
    import torch

    from invphys.inverter.bundle import Bundle
    from invphys.models.data import ModelLoadError

    state = torch.load(bundle / "surrogate" / "weights.pt", weights_only=True)
    key = next(k for k, v in state.items() if v.ndim == 2)
    state[key] = state[key][:-1]
    torch.save(state, bundle / "surrogate" / "weights.pt")
    _rehash(bundle)
    with pytest.raises(ModelLoadError, match=rf"surrogate/weights\.pt: the weights do not fit the saved config "
                                             rf"\({key.replace('.', '[.]')} has shape"):
        Bundle(bundle).surrogate_model()
    # a description far larger than its weights is refused before anything is allocated (meta-device sizes)
    meta = json.loads((bundle / "surrogate" / "model.json").read_text())
    meta["config"]["hidden"] = [10**6, 10**6, 10**6]
    (bundle / "surrogate" / "model.json").write_text(json.dumps(meta))
    _rehash(bundle)
    with pytest.raises(ModelLoadError, match=r"surrogate/weights\.pt: the weights do not fit the saved config"):
        Bundle(bundle).surrogate_model()


@pytest.mark.parametrize("key", ["features.names", "parameter_space.low", "simulator.name",
                                 "components.surrogate.path", "methods.gc.type"])
def test_a_manifest_without_a_required_key_names_it(bundle, key, target_file) -> None:
    from invphys.inverter import BundleError, load_inverter

    def drop(m: dict) -> None:
        *parents, last = key.split(".")
        node = m
        for p in parents:
            node = node[p]
        del node[last]

    _edit(bundle, drop)
    if key == "features.names":
        one_error(invphys("invert", bundle, "--target", target_file), "lacks features.names")
    with pytest.raises(BundleError, match=rf"lacks {key.replace('.', '[.]')}"):
        load_inverter(bundle)


# -- 4. older pickled bundles: refused with the command that converts them --------------------------------------
def _as_format_1_with_sb3_zip(bundle: Path) -> None:
    from invphys.plugins.optimizers import GoalConditionedPPO

    d = bundle / "policies" / "gc"
    GoalConditionedPPO.load(d).model.save(d / "policy.zip")  # SB3's cloudpickled zip, as format 1 kept it
    (d / "policy.npz").unlink()
    _edit(bundle, lambda m: m.update(format_version=1))


def test_an_older_pickled_bundle_is_refused_with_the_upgrade_command(bundle, target_file, tmp_path) -> None:
    from invphys.inverter import load_inverter

    reference = load_inverter(bundle).invert_array(load_inverter(bundle).bundle.data("test")[1][:5], method="gc")
    _as_format_1_with_sb3_zip(bundle)
    line = one_error(invphys("invert", bundle, "--target", target_file), "policies/gc/policy.zip",
                     "would run code", f"invphys export --upgrade {bundle} --out NEW_DIR --trust-pickles")
    assert line.count("error:") == 1
    new = tmp_path / "upgraded"
    one_error(invphys("export", "--upgrade", bundle, "--out", new), "--trust-pickles")
    assert not new.exists()
    res = invphys("export", "--upgrade", bundle, "--out", new, "--trust-pickles", "--json")
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout)["converted"]["gc"].startswith("policies/gc/policy.zip ->")
    assert not (new / "policies" / "gc" / "policy.zip").exists() and (new / "policies" / "gc" / "policy.npz").is_file()
    inv = load_inverter(new)
    assert yaml.safe_load((new / "manifest.yaml").read_text())["format_version"] == 2  # the lowest that holds it
    np.testing.assert_array_equal(inv.invert_array(inv.bundle.data("test")[1][:5], method="gc"), reference)


# -- 5. export never destroys data --------------------------------------------------------------------------------
def test_export_refuses_an_out_that_contains_the_source_even_with_force(toy, tmp_path) -> None:
    home = tmp_path / "home"
    shutil.copytree(toy, home / "inner")
    shutil.copytree(toy, home / "other")  # 'home' itself holds a bundle's manifest: --force would take it
    shutil.copy(home / "other" / "manifest.yaml", home / "manifest.yaml")
    (home / "notes.txt").write_text("mine")
    before = snapshot(home)
    one_error(invphys("export", home / "inner", "--out", home, "--force"), "contains the bundle being exported")
    assert snapshot(home) == before


def test_export_refuses_an_out_inside_the_source(bundle, tmp_path) -> None:
    before = snapshot(bundle)
    one_error(invphys("export", bundle, "--out", bundle / "copy"), "inside the bundle being exported")
    one_error(invphys("export", bundle, "--out", bundle, "--force"), "inside the bundle being exported")
    assert snapshot(bundle) == before


@pytest.mark.parametrize("case", ["under_file", "loop", "under_loop", "symlink", "file", "inside_other_bundle"])
def test_export_to_impossible_or_foreign_places_is_one_error_and_touches_nothing(toy, tmp_path, case) -> None:
    from typer.testing import CliRunner

    from invphys.cli import app

    place = tmp_path / "place"
    place.mkdir()
    (place / "file.txt").write_text("mine")
    (place / "loop").symlink_to(place / "loop")
    (place / "real").mkdir()
    (place / "link").symlink_to(place / "real", target_is_directory=True)
    shutil.copytree(toy, place / "another")
    out = {"under_file": place / "file.txt" / "b", "loop": place / "loop", "under_loop": place / "loop" / "b",
           "symlink": place / "link", "file": place / "file.txt",
           "inside_other_bundle": place / "another" / "b"}[case]
    before = snapshot(place)
    res = CliRunner().invoke(app, ["export", str(toy), "--out", str(out), "--force"])
    assert res.exit_code == 2, res.output
    assert res.output.count("error:") == 1 and "Traceback" not in res.output
    assert snapshot(place) == before
    if case == "under_file":  # the real process too: one line, exit 2
        one_error(invphys("export", toy, "--out", out), "is a file, not a directory")


def test_a_failed_export_leaves_the_old_destination_intact(toy, bundle, tmp_path, monkeypatch) -> None:
    from invphys.inverter import writer
    from invphys.inverter.manifest import read_manifest

    out = tmp_path / "shipped"
    writer.copy_bundle(toy, out, read_manifest(toy)["files"])
    (out / "README.md").write_text("the old bundle's readme")
    _rehash(out)
    before = snapshot(out)
    calls = []
    real_copy = shutil.copy2

    def failing_copy(src, dst, *a, **k):
        calls.append(src)
        if len(calls) > 3:
            raise OSError(28, "No space left on device")
        return real_copy(src, dst, *a, **k)

    monkeypatch.setattr(writer.shutil, "copy2", failing_copy)
    assert writer.export_destination(bundle, out, force=True)
    with pytest.raises(OSError, match="No space left"):
        writer.copy_bundle(bundle, out, read_manifest(bundle)["files"])
    assert snapshot(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bundle", "shipped"]  # no temporary sibling left
    monkeypatch.undo()
    writer.copy_bundle(bundle, out, read_manifest(bundle)["files"])  # --force: the new bundle replaces it
    assert (out / "policies" / "npe" / "npe.json").is_file() and snapshot(out) != before


def test_a_bundle_cannot_name_a_module_for_invphys_to_import(bundle, target_file, tmp_path) -> None:
    """'module:Class' plugin names import code: a bundle's methods and components may name only installed
    plugins, and a module-path simulator that is not imported already is not loaded."""
    marker = tmp_path / "ran.txt"
    (bundle / "evil_plugin.py").write_text(f"open({str(marker)!r}, 'w').write('ran')\n")
    _edit(bundle, lambda m: m["methods"]["cma"].update(type="evil_plugin:Optimizer"))
    res = subprocess.run([sys.executable, "-c", "from invphys.cli import main; main()", "invert", ".", "--target",
                          str(target_file), "--method", "cma"], capture_output=True, text=True, cwd=bundle, timeout=300)
    one_error(res, "methods.cma.type = 'evil_plugin:Optimizer' is a module path")
    _edit(bundle, lambda m: (m["methods"]["cma"].update(type="cma_es"),
                             m["simulator"].update(name="evil_plugin:Simulator")))
    res = subprocess.run([sys.executable, "-c", "from invphys.cli import main; main()", "invert", ".", "--target",
                          str(target_file), "--json"], capture_output=True, text=True, cwd=bundle, timeout=300)
    assert res.returncode == 0, res.stderr
    assert not marker.exists()


def test_a_method_config_its_plugin_rejects_is_one_line_at_load(bundle) -> None:
    from invphys.inverter import BundleError, load_inverter

    _edit(bundle, lambda m: m["methods"]["npe"]["config"].update(samples="many"))
    with pytest.raises(BundleError, match=r"methods\.npe\.config\.samples: Input should be a valid integer"):
        load_inverter(bundle)

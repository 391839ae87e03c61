"""A bundle is written in the lowest manifest format that holds it; a reader of an older format refuses what it
would answer differently (a penalised or started method) instead of silently answering plain CMA-ES."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import yaml

from invphys.inverter import manifest as mf
from invphys.inverter.manifest import BundleError, read_manifest, write_manifest

SHIPPED = Path(__file__).resolve().parents[1] / "inverters" / "orange_peel_quick"


def _copy(tmp_path: Path) -> Path:
    root = tmp_path / "bundle"
    shutil.copytree(SHIPPED, root)
    return root


def _on_disk(root: Path) -> int:
    return yaml.safe_load((root / "manifest.yaml").read_text())["format_version"]


def test_a_bundle_without_the_new_method_keys_stays_format_2_and_reads_migrated(tmp_path: Path) -> None:
    root = _copy(tmp_path)
    write_manifest(root, read_manifest(root))
    assert _on_disk(root) == 2
    assert read_manifest(root)["format_version"] == mf.FORMAT_VERSION == 3


@pytest.mark.parametrize("key,value", [("uncertainty_penalty", 0.5), ("start", "lookup")])
def test_a_method_with_a_format_3_key_makes_the_bundle_format_3(tmp_path: Path, key: str, value: object) -> None:
    root = _copy(tmp_path)
    m = read_manifest(root)
    label = next(iter(m["methods"]))
    m["methods"][label] = {**m["methods"][label], key: value}
    write_manifest(root, m)
    assert _on_disk(root) == 3
    assert read_manifest(root)["methods"][label][key] == value


def test_a_format_2_reader_refuses_a_penalised_bundle_with_upgrade_invphys(tmp_path: Path, monkeypatch) -> None:
    root = _copy(tmp_path)
    m = read_manifest(root)
    label = next(iter(m["methods"]))
    m["methods"][label] = {**m["methods"][label], "uncertainty_penalty": 0.5}
    write_manifest(root, m)
    monkeypatch.setattr(mf, "FORMAT_VERSION", 2)  # the invphys before format 3
    with pytest.raises(BundleError, match=r"has format 3.*reads format 2: upgrade invphys"):
        read_manifest(root)
    m["methods"][label].pop("uncertainty_penalty")
    monkeypatch.setattr(mf, "FORMAT_VERSION", 3)
    write_manifest(root, m)
    monkeypatch.setattr(mf, "FORMAT_VERSION", 2)
    assert read_manifest(root)["format_version"] == 2  # without it, the older reader still reads the bundle

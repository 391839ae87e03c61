"""The one bounded reader (invphys.core.safe_read): what it refuses, quickly and with one line, and what it
accepts (a UTF-8 BOM); specs share its limits through invphys.core.safe_yaml."""

from __future__ import annotations

import io
import json
import os
import threading
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest

from invphys.core import safe_read
from invphys.core.errors import InvphysError, SpecError
from invphys.core.safe_read import (
    UserFileError,
    check_regular_file,
    load_user_json,
    load_user_npz,
    load_user_yaml,
    loads_user_json,
    loads_user_yaml,
    read_user_bytes,
    read_user_csv,
    read_user_text,
)

BOMB = "\n".join(["a: &a [x, x, x, x, x, x, x, x, x, x]"] + [
    f"{chr(98 + i)}: &{chr(98 + i)} [{', '.join(['*' + chr(97 + i)] * 10)}]" for i in range(9)]) + "\n"


def within(seconds: float, fn, *args, **kwargs):
    """``fn(*args, **kwargs)``'s exception (or result), failing the test when it takes longer (a FIFO read
    blocks forever: the reader must never open one)."""
    box: dict[str, object] = {}

    def run() -> None:
        try:
            box["value"] = fn(*args, **kwargs)
        except BaseException as exc:  # handed back to the test
            box["error"] = exc

    t = threading.Thread(target=run, daemon=True)
    t0 = time.perf_counter()
    t.start()
    t.join(seconds)
    assert not t.is_alive(), f"{fn.__name__} still running after {seconds} s"
    box["seconds"] = time.perf_counter() - t0
    return box


def refused(fn, *args, needle: str, seconds: float = 10.0, **kwargs) -> str:
    box = within(seconds, fn, *args, **kwargs)
    err = box.get("error")
    assert isinstance(err, InvphysError), f"not refused: {box}"
    msg = str(err)
    assert len(msg.splitlines()) == 1 and needle in msg, msg
    return msg


# -- not a regular file, too large ---------------------------------------------------------------------------
def test_a_fifo_is_refused_without_blocking(tmp_path) -> None:
    fifo = tmp_path / "t.yaml"
    os.mkfifo(fifo)
    for fn in (check_regular_file, read_user_bytes, read_user_text, load_user_yaml, load_user_json, read_user_csv,
               load_user_npz):
        msg = refused(fn, fifo, what="target file", needle="not a regular file", seconds=5)
        assert msg.startswith(f"target file {str(fifo)!r}: ")


def test_devices_directories_and_missing_files(tmp_path) -> None:
    refused(read_user_bytes, "/dev/zero", what="target file", needle="not a regular file (a device, pipe or socket)")
    refused(read_user_text, "/dev/null", what="manifest", needle="not a regular file")
    refused(read_user_text, tmp_path, what="target file", needle="it is a directory, not a file")
    msg = refused(read_user_text, tmp_path / "absent.json", what="target file", needle="No such file")
    assert msg.startswith("cannot read target file")
    os.symlink("/dev/zero", tmp_path / "zero.json")  # a link to a device: still a device
    refused(load_user_json, tmp_path / "zero.json", what="target file", needle="not a regular file")


def test_a_sparse_file_over_the_limit_is_refused_by_its_size(tmp_path) -> None:
    big = tmp_path / "big.csv"
    with open(big, "wb") as fh:
        fh.truncate(1 << 30)  # 1 GB of nothing: refused by its size, never read
    box = within(5, read_user_csv, big, what="target file")
    assert isinstance(box.get("error"), UserFileError) and float(box["seconds"]) < 2  # type: ignore[arg-type]
    assert "1,073,741,824 bytes, over the 32 MiB limit for a target file" in str(box["error"])
    small = tmp_path / "small.json"
    small.write_text('{"a": 1}')
    refused(load_user_json, small, what="target file", max_bytes=4, needle="over the 4 bytes limit")
    assert load_user_json(small, what="target file", max_bytes=8) == {"a": 1}


# -- text ----------------------------------------------------------------------------------------------------
def test_bom_is_accepted_and_binary_refused_with_its_line(tmp_path) -> None:
    p = tmp_path / "t.csv"
    p.write_bytes(b"\xef\xbb\xbffinal_separation, peak \r\n1.5,2\r\n\r\n3,4\r\n")
    table = read_user_csv(p, what="target file")
    assert table.header == ["final_separation", "peak"] and table.rows == [["1.5", "2"], ["3", "4"]]
    assert table.lines == [2, 4]
    (tmp_path / "t.json").write_bytes(b'\xef\xbb\xbf{"a": 1}')
    assert load_user_json(tmp_path / "t.json", what="target file") == {"a": 1}
    (tmp_path / "t.yaml").write_bytes(b"\xef\xbb\xbfa: 1\n")
    assert load_user_yaml(tmp_path / "t.yaml", what="target file") == {"a": 1}
    (tmp_path / "nul.yaml").write_bytes(b"a: 1\nb: \x00\n")
    refused(load_user_yaml, tmp_path / "nul.yaml", what="target file", needle="NUL byte on line 2")
    (tmp_path / "latin.csv").write_bytes("a\ncaf\xe9\n".encode("latin-1"))
    refused(read_user_csv, tmp_path / "latin.csv", what="target file", needle="not UTF-8 text (byte 0xe9 on line 2)")


# -- YAML ----------------------------------------------------------------------------------------------------
def test_yaml_alias_bomb_and_deep_nesting_are_refused_quickly(tmp_path) -> None:
    (tmp_path / "bomb.yaml").write_text(BOMB)
    refused(load_user_yaml, tmp_path / "bomb.yaml", what="target file", needle="expands to more than", seconds=10)
    refused(loads_user_yaml, BOMB, source="manifest.yaml", needle="manifest.yaml: expands to more than")
    (tmp_path / "deep.yaml").write_text("a: " + "[" * 300 + "]" * 300 + "\n")
    refused(load_user_yaml, tmp_path / "deep.yaml", what="target file", needle="nested too deeply")
    (tmp_path / "loop.yaml").write_text("a: &x [1, *x]\n")
    refused(load_user_yaml, tmp_path / "loop.yaml", what="target file", needle="")


def test_yaml_duplicate_keys_name_both_lines() -> None:
    msg = refused(loads_user_yaml, "a: 1\nb:\n  c: 2\n  c: 3\n", source="t.yaml", needle="")
    assert msg == "t.yaml: key 'c' appears twice in one mapping (lines 3 and 4)"


@pytest.mark.parametrize("text", ["a: " + "9" * 400, "a: -" + "9" * 400, "a: " + "1" + "0" * 309,
                                  "a: 0x" + "f" * 300, "a: " + "9" * 5000])
def test_yaml_integers_too_large_for_a_float_are_refused(text: str) -> None:
    refused(loads_user_yaml, "b: 1\n" + text + "\n", source="t.yaml", needle="on line 2 is too large for a number")
    assert loads_user_yaml("a: " + "9" * 300 + "\n", source="t.yaml")["a"] == int("9" * 300)  # a float holds it


def test_specs_share_the_limits() -> None:
    """The spec reader is the same mechanism: a 400-digit integer in a spec is one SpecError line too."""
    from invphys.core import safe_yaml

    with pytest.raises(SpecError, match=r"the integer 999999999999\.\.\. on line 2 is too large"):
        safe_yaml.load("name: x\nseed: " + "9" * 400 + "\n", source="spec.yaml")
    with pytest.raises(SpecError, match="cannot read spec"):
        safe_yaml.read_text("/nonexistent/spec.yaml")
    with pytest.raises(SpecError, match="not a regular file"):
        safe_yaml.read_text("/dev/zero")


# -- JSON ----------------------------------------------------------------------------------------------------
def test_json_duplicate_keys_name_both_lines(tmp_path) -> None:
    p = tmp_path / "t.json"
    p.write_text('{"targets": [\n  {"a": 1,\n   "b": {"a": 5, "c": 1},\n   "a": 2}\n]}\n')
    msg = refused(load_user_json, p, what="target file", needle="")
    assert msg == f"target file {str(p)!r}: key 'a' appears twice in one object (lines 2 and 4)"
    refused(loads_user_json, '{"x": {"y": 1, "y": 2}}', source="h", needle="h: key 'y' appears twice in one object")
    assert loads_user_json('{"a": {"a": 1}, "b": [{"a": 2}, {"a": 3}]}', source="ok")["b"][1] == {"a": 3}


def test_json_huge_integers_refused_nan_read_as_float() -> None:
    refused(loads_user_json, '{"a": ' + "9" * 400 + "}", source="t.json", needle="(400 digits) is too large")
    refused(loads_user_json, '[-' + "9" * 5000 + "]", source="t.json", needle="too large for a number")
    refused(loads_user_json, "[" + "1" + "0" * 309 + "]", source="t.json", needle="too large for a number")
    data = loads_user_json('{"a": NaN, "b": -Infinity, "c": 1e999}', source="t.json")
    assert np.isnan(data["a"]) and data["b"] == -np.inf and data["c"] == np.inf  # the caller decides (targets refuse)
    refused(loads_user_json, "[" * 100_000 + "]" * 100_000, source="t.json", needle="")
    refused(loads_user_json, "{oops", source="t.json", needle="t.json: not valid JSON (line 1")


# -- CSV -----------------------------------------------------------------------------------------------------
def test_csv_duplicate_columns_name_both(tmp_path) -> None:
    p = tmp_path / "t.csv"
    p.write_text("id,final_separation,peak, final_separation\n1,2,3,4\n")
    msg = refused(read_user_csv, p, what="target file", needle="")
    assert msg == f"target file {str(p)!r}: columns 2 and 4 are both named 'final_separation'"
    (tmp_path / "empty.csv").write_text("\n")
    refused(read_user_csv, tmp_path / "empty.csv", what="target file", needle="empty CSV")
    (tmp_path / "field.csv").write_text("a\n" + "x" * 200_000 + "\n")  # over the csv module's field limit
    refused(read_user_csv, tmp_path / "field.csv", what="target file", needle="not valid CSV")


# -- NumPy archives ------------------------------------------------------------------------------------------
def test_npz_truncated_bombs_pickles_and_strangers_are_refused(tmp_path) -> None:
    good = tmp_path / "good.npz"
    np.savez_compressed(good, a=np.arange(10), b=np.ones((2, 3)))
    arrays = load_user_npz(good, what="trajectory")
    assert sorted(arrays) == ["a", "b"] and arrays["a"].tolist() == list(range(10))
    data = good.read_bytes()
    for cut in (len(data) // 2, len(data) - 10, 30):
        (tmp_path / "cut.npz").write_bytes(data[:cut])
        refused(load_user_npz, tmp_path / "cut.npz", what="trajectory", needle="truncated or corrupt")
    buf = io.BytesIO()  # a small archive whose array unpacks to 100 MB
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        with zf.open("a.npy", "w", force_zip64=True) as fh:
            np.lib.format.write_array_header_1_0(fh, {"descr": "<f8", "fortran_order": False, "shape": (12_500_000,)})
            for _ in range(100):
                fh.write(bytes(1_000_000))
    (tmp_path / "bomb.npz").write_bytes(buf.getvalue())
    assert (tmp_path / "bomb.npz").stat().st_size < 1_000_000
    refused(load_user_npz, tmp_path / "bomb.npz", what="trajectory", max_unpacked=10_000_000, needle="unpacks to")
    np.savez(tmp_path / "pickle.npz", a=np.array([{"x": 1}], dtype=object))
    refused(load_user_npz, tmp_path / "pickle.npz", what="trajectory", needle="array 'a' holds pickled objects")
    buf = io.BytesIO()  # a member whose header claims 800 GB (NumPy would allocate it before reading)
    with zipfile.ZipFile(buf, "w") as zf, zf.open("a.npy", "w") as fh:
        np.lib.format.write_array_header_1_0(fh, {"descr": "<f8", "fortran_order": False, "shape": (10**11,)})
        fh.write(bytes(64))
    (tmp_path / "claim.npz").write_bytes(buf.getvalue())
    refused(load_user_npz, tmp_path / "claim.npz", what="trajectory", needle="claims 800,000,000,000 bytes")
    with zipfile.ZipFile(tmp_path / "zip.npz", "w") as zf:
        zf.writestr("run.sh", "echo hi")
    refused(load_user_npz, tmp_path / "zip.npz", what="trajectory", needle="holds other files than arrays")
    (tmp_path / "text.npz").write_text(json.dumps({"a": 1}))
    refused(load_user_npz, tmp_path / "text.npz", what="trajectory", needle="not a readable .npz archive")


def test_limits_are_documented_numbers() -> None:
    assert safe_read.DEFAULT_MAX_BYTES == 32 << 20 and safe_read.YAML_MAX_BYTES == 4 << 20
    assert safe_read.NPZ_MAX_BYTES == 2 << 30 and safe_read.NPZ_MAX_UNPACKED == 4 << 30
    assert isinstance(UserFileError("target file", Path("t.csv"), "x"), InvphysError)


def test_a_large_limit_costs_no_memory_of_its_own(tmp_path: Path) -> None:
    """Reading a small file under a 2 GiB limit must not allocate the limit (a process capped at 1 GiB)."""
    import subprocess
    import sys

    small = tmp_path / "small.bin"
    small.write_bytes(b"x" * 1000)
    code = ("import resource; resource.setrlimit(resource.RLIMIT_AS, (1 << 30, 1 << 30)); "
            "from invphys.core.safe_read import read_user_bytes; "
            f"print(len(read_user_bytes({str(small)!r}, what='file', max_bytes=2 << 30)))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-500:]
    assert out.stdout.strip() == "1000"

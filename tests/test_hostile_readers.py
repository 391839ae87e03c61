"""Hostile and careless files handed to real `invphys invert --target FILE` and `invphys render` processes:
each class ends in exit 2 and one `error:` line naming the file and the problem, within seconds, with no
traceback, nothing written, and the user's files byte-identical afterwards (the bounded reader,
invphys.core.safe_read)."""

from __future__ import annotations

import hashlib
import json
import os
import stat
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
QUICK = ROOT / "inverters" / "orange_peel_quick"
FEATURES = ("final_separation", "peak_separation_rate")
BOMB = "\n".join(["a: &a [x, x, x, x, x, x, x, x, x, x]"] + [
    f"{chr(98 + i)}: &{chr(98 + i)} [{', '.join(['*' + chr(97 + i)] * 10)}]" for i in range(9)]) + "\n"


def snapshot(root: Path) -> dict[str, str]:
    """Every path under ``root`` with a hash of a regular file's bytes (a FIFO is never opened; a file over
    1 MiB, the sparse one, by its size and modification time)."""
    out = {}
    for p in sorted(root.rglob("*")):
        st = os.lstat(p)
        if stat.S_ISREG(st.st_mode) and st.st_size > 1 << 20:
            out[str(p.relative_to(root))] = f"{st.st_size}:{st.st_mtime_ns}"
        elif stat.S_ISREG(st.st_mode):
            out[str(p.relative_to(root))] = hashlib.sha256(p.read_bytes()).hexdigest()
        else:
            out[str(p.relative_to(root))] = "link" if p.is_symlink() else "dir" if p.is_dir() else "special"
    return out


def run_cli(args: list[str], cwd: Path, needle: str) -> str:
    before = snapshot(cwd)
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "invphys.cli", *args], capture_output=True, text=True,
                          timeout=60, cwd=cwd, stdin=subprocess.DEVNULL)
    seconds = time.perf_counter() - t0
    err = proc.stderr.strip()
    assert proc.returncode == 2, f"exit {proc.returncode}: {err[-2000:]}"
    assert "Traceback" not in err and len(err.splitlines()) == 1 and err.startswith("error:"), err[-2000:]
    assert needle in err, err
    assert proc.stdout == "" and seconds < 30, seconds
    assert snapshot(cwd) == before  # nothing written, nothing changed
    return err


# -- invphys invert BUNDLE --target FILE --------------------------------------------------------------------
def _fifo(p: Path) -> None:
    os.mkfifo(p)


def _sparse(p: Path) -> None:
    with open(p, "wb") as fh:
        fh.truncate(1 << 30)


def _text(text: str) -> Callable[[Path], None]:
    return lambda p: p.write_text(text)


TARGET_CASES: dict[str, tuple[str, Callable[[Path], None], str]] = {
    "fifo": ("t.yaml", _fifo, "not a regular file"),
    "device-link": ("zero.json", lambda p: os.symlink("/dev/zero", p), "not a regular file"),
    "directory": ("dir.csv", lambda p: p.mkdir(), "it is a directory"),
    "sparse-1gb": ("big.csv", _sparse, "1,073,741,824 bytes, over the 32 MiB limit"),
    "alias-bomb": ("bomb.yaml", _text(BOMB), "expands to more than"),
    "deep-nesting": ("deep.yaml", _text("a: " + "[" * 500 + "]" * 500 + "\n"), "nested too deeply"),
    "duplicate-yaml-key": ("d.yaml", _text(f"{FEATURES[0]}: 1\n{FEATURES[1]}: 2\n{FEATURES[0]}: 3\n"),
                           f"key '{FEATURES[0]}' appears twice in one mapping (lines 1 and 3)"),
    "duplicate-json-key": ("d.json", _text(f'{{"{FEATURES[0]}": 1,\n"{FEATURES[1]}": 2,\n"{FEATURES[0]}": 3}}'),
                           f"key '{FEATURES[0]}' appears twice in one object (lines 1 and 3)"),
    "duplicate-csv-column": ("d.csv", _text(f"{FEATURES[0]},{FEATURES[1]},{FEATURES[0]}\n1,2,3\n"),
                             f"columns 1 and 3 are both named '{FEATURES[0]}'"),
    "int400-yaml": ("i.yaml", _text(f"{FEATURES[0]}: {'9' * 400}\n"), "too large for a number"),
    "int400-json": ("i.json", _text(f'{{"{FEATURES[0]}": {"9" * 400}}}'), "too large for a number"),
    "int5000-json": ("j.json", _text(f'[{{"{FEATURES[0]}": {"9" * 5000}}}]'), "too large for a number"),
    "nul-byte": ("n.csv", lambda p: p.write_bytes(f"{FEATURES[0]}\n1\x00\n".encode()), "NUL byte on line 2"),
}


@pytest.mark.parametrize("case", sorted(TARGET_CASES))
def test_invert_target_file(case: str, tmp_path: Path) -> None:
    name, make, needle = TARGET_CASES[case]
    (tmp_path / "mine.csv").write_text("a,b\n1,2\n")  # a user's own file beside it: must stay as it is
    make(tmp_path / name)
    err = run_cli(["invert", str(QUICK), "--target", name, "--partial"], tmp_path, needle)
    assert name in err


# -- invphys render TRAJECTORY ------------------------------------------------------------------------------
def _trajectory_bytes() -> bytes:
    from invphys.core.results import TimeSeries, Trajectory
    from invphys.core.trajectory_io import to_bytes

    traj = Trajectory(series={"gap": TimeSeries(times=np.arange(5.0), values=np.linspace(0, 1, 5))},
                      positions=np.zeros((3, 4, 3)), damage=np.zeros((3, 4)), labels=np.zeros(4, np.int8),
                      frame_indices=np.arange(3), fps=10.0)
    return to_bytes(traj, {"simulator": "orange_peel", "version": "0", "config": {}})


def _npz(**arrays: np.ndarray) -> Callable[[Path], None]:
    return lambda p: np.savez(p, **arrays)


RENDER_CASES: dict[str, tuple[Callable[[Path], None], str]] = {
    "truncated": (lambda p: p.write_bytes(_trajectory_bytes()[:-200]), "truncated or corrupt"),
    "half": (lambda p: p.write_bytes(_trajectory_bytes()[: len(_trajectory_bytes()) // 2]), "truncated or corrupt"),
    "fifo": (_fifo, "not a regular file"),
    "pickle": (_npz(header=np.array([{"x": 1}], dtype=object)), "not a trajectory file"),
    "header-not-an-object": (_npz(header=np.array("[1, 2]")), "its header is not a JSON object"),
    "header-duplicate-key": (_npz(header=np.array('{"format": "invphys.trajectory", "format": "x"}')),
                             "appears twice"),
    "shapes-disagree": (_npz(header=np.array(json.dumps({"format": "invphys.trajectory", "version": 1, "fps": 10,
                                                         "series": [], "fields": []})),
                             positions=np.zeros((3, 4, 3)), damage=np.zeros((5, 5)), frame_indices=np.arange(3)),
                        "damage must be (3, 4)"),
}


@pytest.mark.parametrize("case", sorted(RENDER_CASES))
def test_render_trajectory(case: str, tmp_path: Path) -> None:
    make, needle = RENDER_CASES[case]
    make(tmp_path / "trajectory.npz")
    err = run_cli(["render", "trajectory.npz", "--out", "drawn"], tmp_path, needle)
    assert "trajectory.npz" in err and not (tmp_path / "drawn").exists()

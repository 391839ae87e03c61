"""``invert_many(workers=N)`` and ``invphys invert --workers N``: targets answered by worker processes that each
load the bundle give the answers of one process, in target order (shipped paper bundle, a private copy;
the toy bundle on the command line)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_inverter_support import paper_inverter, toy_run

from invphys.core.errors import InvphysError
from invphys.inverter.parallel import check_workers, slices


@pytest.fixture(scope="module")
def inv(tmp_path_factory):
    return paper_inverter(tmp_path_factory.getbasetemp())


def _key(results) -> list:
    return [(r.label, r.method, r.theta.tolist(), r.r_surrogate,
             [(c.theta.tolist(), c.r_surrogate) for c in r.candidates]) for r in results]


def test_workers_give_the_answers_of_one_process_in_target_order(inv) -> None:
    _, y = inv.bundle.data("test")
    y = y[:9]
    ticks: dict[str, list[int]] = {"serial": [], "workers": []}
    serial = inv.invert_many(y, top_k=2, on_answer=ticks["serial"].append)
    assert _key(inv.invert_many(y, top_k=2, workers=2, on_answer=ticks["workers"].append)) == _key(serial)
    assert ticks["serial"] == [1] * 9 and sum(ticks["workers"]) == 9 and len(ticks["workers"]) == 8  # per slice
    pool = inv.__dict__["_answer_pool"][1]
    # the processes are kept for the next call, which carries the inverter's current pool settings
    from dataclasses import replace

    inv.pool_settings = replace(inv.pool_settings, draws=32)
    try:
        assert _key(inv.invert_many(y[:5], method="pool", workers=2)) == _key(inv.invert_many(y[:5], method="pool"))
        assert inv.__dict__["_answer_pool"][1] is pool
        from invphys.inverter.parallel import close_workers

        close_workers(inv)   # the processes are shut down; the next call with workers starts new ones
        assert "_answer_pool" not in inv.__dict__
        assert _key(inv.invert_many(y[:3], top_k=2, workers=2)) == _key(serial[:3])
        assert inv.__dict__["_answer_pool"][1] is not pool
    finally:
        inv.pool_settings = replace(inv.pool_settings, draws=64)


def test_workers_run_native_pools_on_the_inverters_threads(inv) -> None:
    """Each worker's BLAS/OpenMP/torch pools get the inverter's ``threads`` (default one) for its whole life,
    however few targets a slice holds: left at one per core, 16 workers on a 16-core host ran 256 threads."""
    from invphys.core.threads import native_threads

    _, y = inv.bundle.data("test")
    inv.invert_many(y[:4], top_k=2, workers=2)   # slices of 1 row: below the batches that limit BLAS
    got = inv.__dict__["_answer_pool"][1].submit(native_threads).result()
    assert got["pools"] == [1] and got["torch"] == 1 and got["env"]["OMP_NUM_THREADS"] == "1"
    inv.threads = 2
    try:
        inv.invert_many(y[:4], top_k=2, workers=2)   # other threads: new workers
        got = inv.__dict__["_answer_pool"][1].submit(native_threads).result()
        assert got["pools"] == [2] and got["torch"] == 2
    finally:
        inv.threads = 1


def test_a_bad_worker_count_is_one_line(inv) -> None:
    for bad in (-1, 1.5, True, 10_000):
        with pytest.raises(InvphysError, match="workers must be a whole number"):
            inv.invert_many(np.zeros((2, len(inv.feature_names))), workers=bad)
    assert check_workers(0) == 0 and check_workers(np.int64(3)) == 3


def test_slices_are_contiguous_and_cover_every_target_once() -> None:
    got = slices(10, 2)
    assert len(got) == 8 and np.concatenate(got).tolist() == list(range(10))
    assert [len(s) for s in slices(3, 4)] == [1, 1, 1]


def test_invert_workers_on_the_command_line(tmp_path_factory, tmp_path) -> None:
    from typer.testing import CliRunner

    import invphys
    from invphys.cli import app
    from invphys.core.dataset import DatasetStore

    run = toy_run(tmp_path_factory.getbasetemp())
    bundle = run / "inverter"
    y = DatasetStore(next((run / "dataset").rglob("_manifest.json")).parent).arrays(ok_only=True).y[:6]
    names = invphys.load_inverter(bundle).feature_names
    targets = tmp_path / "targets.json"
    targets.write_text(json.dumps([dict(zip(names, map(float, row), strict=True)) for row in y]))
    runner = CliRunner()
    answers = []
    for workers in ("0", "2"):
        out = runner.invoke(app, ["invert", str(bundle), "--target", str(targets), "--workers", workers, "--json"])
        assert out.exit_code == 0, out.output
        assert "answering" in out.stderr and "6/6" in out.stderr   # the progress bar, on stderr
        answers.append([(r["candidates"][0]["parameters"], r["candidates"][0]["r_surrogate"])
                        for r in json.loads(out.stdout)["results"]])
    assert answers[0] == answers[1] and len(answers[0]) == 6
    out = runner.invoke(app, ["invert", str(bundle), "--target", str(targets), "--workers", "-1"])
    assert out.exit_code == 2 and "--workers" in out.output and "Traceback" not in out.output, out.output


def test_a_script_without_a_main_guard_gets_one_line_that_says_so(inv, tmp_path) -> None:
    """Spawned workers import the calling script; one without ``if __name__ == "__main__":`` kills them at start."""
    import subprocess
    import sys

    script = tmp_path / "unguarded.py"
    script.write_text("import invphys\n"
                      f"inv = invphys.load_inverter({str(inv.bundle.root)!r})\n"
                      "_, y = inv.bundle.data('test')\n"
                      "inv.invert_many(y[:4], workers=2)\n")
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=600)
    assert done.returncode != 0
    error = [line for line in done.stderr.splitlines() if line.startswith("invphys.core.errors.InvphysError: ")]
    assert len(error) == 1 and "a worker process died while answering" in error[0]
    assert "if __name__ == \"__main__\":" in error[0]   # (the interpreter may warn after it at exit)

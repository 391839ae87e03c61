"""What benchmark JSONs record about the machine they ran on, and how they are written."""

from __future__ import annotations

import platform
from pathlib import Path


def cpu_name() -> str:
    """The CPU's model name (from /proc/cpuinfo where there is one), else ``platform.processor()``."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def simulator_device(sim: object) -> str:
    """A simulator's device as a result records it: the GPU's name and the engine's device on CUDA, else the
    engine's device, else the CPU's name (a simulator with no engine yet reads as the CPU)."""
    import subprocess

    dev = ""
    try:
        dev = str(sim.engine.device)  # type: ignore[attr-defined]
    except Exception:  # a simulator without a warm engine
        pass
    try:
        names = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True,
                               text=True, timeout=30).stdout.strip().splitlines()
        if names and dev.startswith("cuda"):
            return f"{names[0]} ({dev})"
    except (OSError, subprocess.SubprocessError):
        pass
    return dev if dev and dev != "cpu" else f"cpu ({cpu_name()})"


def sim_options(items: list[str]) -> dict[str, object]:
    """``KEY=VALUE`` simulator overrides (``--sim-option``), each value read as YAML."""
    import yaml

    return {k: yaml.safe_load(v) for k, _, v in (i.partition("=") for i in items)}


def provenance() -> dict[str, str]:
    """The running script (relative to the repository) and its command line, as a committed result names them
    (``benchmarks/README.md``)."""
    import shlex
    import sys

    script = Path(sys.argv[0]).resolve()
    root = Path(__file__).resolve().parent.parent
    rel = script.relative_to(root).as_posix() if script.is_relative_to(root) else script.name
    return {"script": rel, "command": shlex.join(["python", rel, *sys.argv[1:]])}


def emit(result: dict, out: Path | None) -> None:
    """Print a benchmark's JSON and, with ``out``, write it there (parent folders made). The JSON starts with
    the script and command that made it, unless the result names them already."""
    import json

    result = {**provenance(), **result}
    text = json.dumps(result, indent=1) + "\n"
    if out:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text)
    print(text)

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

"""Run every benchmark in bench/ and collect their results in one JSON object.

Each benchmark (a ``bench/*.py`` script with a ``__main__`` guard, other than this runner and
``table.py``) runs as a subprocess of this interpreter from the repository root, with its full
arguments or, with ``--quick``, its small variant (see ``FULL`` and ``QUICK``). Its stdout must
be one JSON object; its stderr streams through to the console. The collected object

    {"<name>": {"command": ..., "argv": [...], "seconds": ..., "result": {...}}, ...,
     "_meta": {"date": ..., "commit": ..., "cpu_count": ..., "platform": ..., ...}}

goes to stdout and to ``bench/out/all.json`` (rewritten after each benchmark, so finished
results survive an interruption). A failed benchmark (non-zero exit, or stdout that is not one
JSON object) gets ``"error"`` and the tail of its stderr instead of ``"result"``; the others
still run and the exit status is 1.

Usage: ``python bench/all.py [--quick] [--only NAME ...] [--out PATH]`` (``--only`` runs the
named benchmarks in the order given, e.g. the longest first); then
``python bench/table.py --write-readme`` puts the tables into docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import collections
import datetime
import json
import os
import platform
import shlex
import subprocess
import sys
import threading
import time
from pathlib import Path

from measures import cpu_model

BENCH = Path(__file__).resolve().parent
ROOT = BENCH.parent
OUT = BENCH / "out" / "all.json"
NOT_BENCHMARKS = {"all", "table"}
FULL: dict[str, list[str]] = {"registration": ["--ablation-sequences", "1"]}
"""Arguments of the full runs (the ones docs/benchmarks.md publishes); others run without any."""
QUICK: dict[str, list[str]] = {
    "calibration": ["--views", "90"],
    "detector": [
        "--frames",
        "60",
        "--gone-trials",
        "2",
        "--views",
        "90",
        "--panel",
        "128",
        "--voxel-mm",
        "2",
    ],
    "iterative": ["--quick"],
    "mar": ["--views", "90"],
    "motion": ["--small", "--seeds", "1", "--sizes", "0", "4"],
    "recon": ["--small"],
    "registration": ["--quick"],
    "scan": ["--small"],
    "soak": ["--scans", "3"],
}
"""Arguments of the small variants (``--quick``); others run as in ``FULL``."""
STDERR_TAIL_LINES = 40


def benchmarks() -> list[str]:
    """Names of the benchmark scripts in bench/, sorted."""
    return sorted(
        path.stem
        for path in BENCH.glob("*.py")
        if path.stem not in NOT_BENCHMARKS
        and not path.stem.startswith("_")
        and "__main__" in path.read_text()
    )


def arguments(name: str, quick: bool) -> list[str]:
    """Command-line arguments of one benchmark."""
    if quick and name in QUICK:
        return list(QUICK[name])
    return list(FULL.get(name, []))


def git_commit() -> tuple[str | None, bool | None]:
    """Short hash of HEAD and whether tracked files have uncommitted changes (None outside git)."""
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
        status = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None, None
    return commit, bool(status)


def machine() -> dict:
    """Facts about this machine and interpreter."""
    return {
        "cpu_count": os.cpu_count(),
        "cpu_model": cpu_model(),
        "platform": platform.platform(),
        "machine": platform.machine(),
        "processor": platform.processor() or None,
        "python": platform.python_version(),
    }


def _pump(stream, tail: collections.deque) -> None:
    """Copy a child's stderr to ours line by line, keeping the last lines."""
    for line in stream:
        sys.stderr.write(line)
        sys.stderr.flush()
        tail.append(line)


def run(name: str, args: list[str]) -> dict:
    """Run one benchmark; its record (``result`` or ``error``) with command and wall time."""
    script = f"bench/{name}.py"
    argv = [sys.executable, script, *args]
    record: dict = {"command": shlex.join(["python", script, *args]), "argv": argv}
    print(f"[bench/all] {name}: {record['command']}", file=sys.stderr, flush=True)
    tail: collections.deque[str] = collections.deque(maxlen=STDERR_TAIL_LINES)
    start = time.perf_counter()
    with subprocess.Popen(
        argv, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    ) as process:
        pump = threading.Thread(target=_pump, args=(process.stderr, tail), daemon=True)
        pump.start()
        stdout = process.stdout.read()
        returncode = process.wait()
        pump.join()
    record["seconds"] = round(time.perf_counter() - start, 1)
    record["returncode"] = returncode
    error = None
    if returncode:
        error = f"exit status {returncode}"
    else:
        try:
            result = json.loads(stdout)
        except json.JSONDecodeError as exc:
            error = f"stdout is not one JSON object ({exc})"
        else:
            if isinstance(result, dict):
                record["result"] = result
            else:
                error = f"stdout is JSON but not an object ({type(result).__name__})"
    if error:
        record["error"] = error
        record["stderr_tail"] = "".join(tail)
        record["stdout_tail"] = stdout[-2000:]
    state = f"failed: {error}" if error else "done"
    print(f"[bench/all] {name}: {state} in {record['seconds']} s", file=sys.stderr, flush=True)
    return record


def main() -> int:
    available = benchmarks()
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the small variants")
    parser.add_argument("--only", nargs="+", metavar="NAME", choices=available)
    parser.add_argument("--out", type=Path, default=OUT, help=f"default: {OUT.relative_to(ROOT)}")
    args = parser.parse_args()
    names = list(dict.fromkeys(args.only)) if args.only else available

    out: dict = {}
    commit, dirty = git_commit()
    meta = {
        "date": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
        "commit": commit,
        "dirty": dirty,
        "quick": args.quick,
        "benchmarks": names,
        **machine(),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    for name in names:
        out[name] = run(name, arguments(name, args.quick))
        meta["seconds"] = round(time.perf_counter() - started, 1)
        args.out.write_text(json.dumps(out | {"_meta": meta}, indent=1) + "\n")
    text = json.dumps(out | {"_meta": meta}, indent=1)
    print(text)
    failed = [n for n, r in out.items() if "error" in r]
    if failed:
        print(f"[bench/all] failed: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())

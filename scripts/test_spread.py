"""The spread of the accuracy tests' figures over seeds, numba thread counts and CPU code paths.

Every test that checks an accuracy figure (``measured`` in tests/conftest.py, marker
``accuracy``; ``-m`` takes another marker expression, e.g. ``accuracy`` for the slow ones too)
is run once per combination, each run a ``pytest -m "accuracy and not slow" --seed S`` process
with ``NUMBA_NUM_THREADS`` and the CPU profile set:

- ``native``: the code paths this machine picks (numba compiles for the host CPU, OpenBLAS
  chooses its kernels);
- ``haswell``: numba compiles for Haswell (``NUMBA_CPU_NAME``) and OpenBLAS takes its Haswell
  kernels (``OPENBLAS_CORETYPE``): the code paths of a CPU without AVX-512, as many laptops and
  older servers have.

Every figure is recorded (``CBCT_TEST_FIGURES``; with ``CBCT_TEST_FIGURES_ONLY`` a figure
out of bounds does not stop its test, so the ones after it are measured too). Printed: a table
of each figure's bound, its worst value over the runs and the margin (bound / worst - 1 for an
upper bound, worst / bound - 1 for a lower one; the suite asks for at least 10 %); ``--out``
writes the rows as JSON.

Usage: ``python scripts/test_spread.py [--seeds 0,1,2] [--threads 1,2] [--cpus native,haswell]
[-k EXPR] [-m EXPR] [--out spread.json]``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
CPUS = {
    "native": {},
    "haswell": {"NUMBA_CPU_NAME": "haswell", "OPENBLAS_CORETYPE": "Haswell"},
}
MARGIN = 0.10
"""The least margin of a bound over its figure's worst value (the suite's rule)."""


def run(seed: int, threads: int, cpu: str, select: str | None, marker: str, figures: Path) -> dict:
    """One pytest run of the accuracy tests; its outcome."""
    env = dict(os.environ, NUMBA_NUM_THREADS=str(threads), CBCT_TEST_FIGURES=str(figures))
    env["CBCT_TEST_FIGURES_ONLY"] = "1"  # every figure of a test, also after one out of bounds
    env.update(CPUS[cpu])
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--seed", str(seed)]
    cmd += ["-m", marker]
    if select:
        cmd += ["-k", select]
    started = time.perf_counter()
    done = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, check=False)
    summary = done.stdout.strip().splitlines()[-1] if done.stdout.strip() else done.stderr[-300:]
    return {
        "seed": seed,
        "numba_threads": threads,
        "cpu": cpu,
        "exit_code": done.returncode,
        "summary": summary,
        "seconds": round(time.perf_counter() - started, 1),
    }


def spread(rows: list[dict]) -> list[dict]:
    """Per test and figure: its bound, the values' range and the margin of the bound."""
    groups: dict[tuple[str, str], list[dict]] = defaultdict(list)
    for row in rows:
        groups[(row["test"], row["figure"])].append(row)
    out = []
    for (test, figure), items in sorted(groups.items()):
        values = [r["value"] for r in items]
        below, above = items[0]["below"], items[0]["above"]
        entry = {
            "test": test,
            "figure": figure,
            "runs": len(values),
            "min": min(values),
            "max": max(values),
            "below": below,
            "above": above,
        }
        margins = []
        if below is not None:
            worst = max(values)
            margins.append(below / worst - 1.0 if worst > 0 else float("inf"))
        if above is not None:
            worst = min(values)
            margins.append(worst / above - 1.0 if above > 0 else float("inf"))
        entry["margin"] = min(margins) if margins else None
        out.append(entry)
    return out


def table(entries: list[dict]) -> str:
    lines = [
        "| test | figure | bound | min | max | margin |",
        "|---|---|---|---|---|---|",
    ]
    for e in entries:
        bound = " ".join(
            f"{word} {value:g}"
            for word, value in (("<", e["below"]), (">", e["above"]))
            if value is not None
        )
        margin = e["margin"]
        shown = "-" if margin is None else f"{100 * margin:.0f} %"
        if margin is not None and margin < MARGIN:
            shown = f"**{shown}**"
        test = e["test"].split("::", 1)[1]
        lines.append(
            f"| {test} | {e['figure']} | {bound} | {e['min']:.4g} | {e['max']:.4g} | {shown} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--threads", default="1,2")
    parser.add_argument("--cpus", default=",".join(CPUS))
    parser.add_argument("-k", dest="select", default=None, help="pytest -k expression")
    parser.add_argument(
        "-m", dest="marker", default="accuracy and not slow", help="pytest -m expression"
    )
    parser.add_argument("--out", type=Path, default=None, help="write the rows as JSON here")
    args = parser.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    threads = [int(t) for t in args.threads.split(",")]
    cpus = args.cpus.split(",")
    unknown = sorted(set(cpus) - set(CPUS))
    if unknown:
        parser.error(f"unknown CPU profiles {unknown}; profiles are {sorted(CPUS)}")
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        figures = Path(tmp) / "figures.jsonl"
        for cpu in cpus:
            for n in threads:
                for seed in seeds:
                    outcome = run(seed, n, cpu, args.select, args.marker, figures)
                    runs.append(outcome)
                    print(json.dumps(outcome), file=sys.stderr, flush=True)
        if not figures.exists():
            raise SystemExit(
                f"no test recorded a figure (pytest -m {args.marker!r}"
                + (f" -k {args.select!r}" if args.select else "")
                + f": {runs[-1]['summary']}): only tests that use `measured` record figures"
            )
        rows = [json.loads(line) for line in figures.read_text(encoding="utf-8").splitlines()]
    entries = spread(rows)
    print(table(entries))
    if args.out is not None:
        payload = {"runs": runs, "figures": entries, "rows": rows}
        args.out.write_text(json.dumps(payload, indent=1), encoding="utf-8")


if __name__ == "__main__":
    main()

"""Benchmark: ``cbct batch all`` over a small simulated cohort on 1 and 2 local workers.

Makes ``--studies`` studies once (the demo's acquisitions at ``study.batch.TINY``, seeds
1..N, on a 2-worker LocalCluster), then for W = 1 and 2 hard-links fresh copies and times
``study.batch.run(..., "all")`` on a LocalCluster of W single-threaded worker processes (the
same code ``cbct batch`` runs). Before the clock starts each cluster is up (``cluster_start_s``)
and each worker has run every task once on its own copy of a study (``warm_s``: imports and
numba's cached kernels, a start-up a long cohort amortises). Scaling efficiency 1 -> 2
workers: ``wall_1 / (2 * wall_2)``; ``load_avg_1min_*`` (about W when
nothing else runs) tells whether anything else ran.

Projection to N machines of W workers each, studies on shared storage, from the measured
per-study costs (JSON ``projection``; every input in it):

    wall(S, N, W) = max( ceil(S / (N W)) * (t_study / e + b_study / (link / W)),
                         S * b_study / storage )

``t_study``: the mean task seconds of one study on the single worker (recon + register +
assess), ``e``: the measured 1 -> 2 worker efficiency on one machine (memory bandwidth and
caches the cores share), ``b_study``: bytes one study's tasks read and write (acquisitions
read, derived folders written, intermediates read back by the next task), ``link``: each
machine's network bandwidth (its W workers share it), ``storage``: the shared storage's
aggregate bandwidth. Scheduler cost per task (~1 ms) is left out: tasks last seconds.

Prints one JSON object. Usage: ``python bench/cohort.py [--studies 4] [--light] [--keep DIR]``
(``--light`` uses the tests' cheaper registration settings).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from distributed import Client  # noqa: E402

from configs import CONFIGS  # noqa: E402
from registration.settings import Settings  # noqa: E402
from study import batch  # noqa: E402

LIGHT = Settings(
    pyramid_mm=(2.4,),
    de_popsize=5,
    de_maxiter=5,
    powell_maxfev=60,
    nelder_mead_maxfev=20,
    passes=1,
    drop_ncc=1.0,
)
"""The tests' registration settings (a fraction of the default search)."""
LINK_BYTES_S = 125e6
"""Assumed network bandwidth of each machine: 1 Gbit/s, B/s."""
STORAGE_BYTES_S = 1e9
"""Assumed aggregate bandwidth of the shared storage (e.g. an NFS server on 10 GbE), B/s."""
LOAD_SAMPLE_S = 5.0
"""How often the 1-minute load average is sampled during a run, s (W when nothing else runs)."""
PROJECTED_STUDIES = 100
MACHINES = (1, 2, 4, 8, 16)
READ = (
    "scan/projections.mha",
    "scan/geometry.xml",
    "scan/true_geometry.xml",
    "calibration/",
    "fluoro/frames.mha",
    "fluoro/view.xml",
    "fluoro/poses.csv",
)
"""What a study's tasks read of its acquisitions."""
WRITTEN = ("recon/", "segmentation/", "registration/", "assessment/")
READ_BACK = (
    "recon/volume.nii.gz",  # register
    "segmentation/labels.nii.gz",  # register
    "segmentation/labels.nii.gz",  # assess
    "registration/poses.csv",  # assess
)
"""Derived files a later task of the study reads again."""


def say(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def size_of(study: Path, names: tuple[str, ...]) -> int:
    """Bytes of the named files and folders of a study."""
    total = 0
    for name in names:
        path = study / name
        if path.is_dir():
            total += sum(p.stat().st_size for p in path.rglob("*") if p.is_file())
        elif path.is_file():
            total += path.stat().st_size
    return total


def warm(client: Client, acquired: Path, dst: Path, options: batch.TaskOptions) -> float:
    """Run every task once on each worker, on its own hard-linked copy of one acquired study
    (imports, numba's cached kernels loaded; the light registration is enough for that): the
    per-worker start-up a long cohort amortises, kept out of the timed run. Returns the wall
    seconds."""
    started = time.perf_counter()
    last = []
    for i, address in enumerate(client.scheduler_info()["workers"]):
        copy = dst / f"worker-{i}"
        shutil.copytree(acquired, copy, copy_function=os.link)
        previous = None
        for task in batch.ACTIONS["all"]:
            previous = client.submit(
                batch.run_task,
                str(copy),
                task,
                options,
                previous,
                workers=[address],
                allow_other_workers=False,
                pure=False,
            )
        last.append(previous)
    client.gather(last)
    return time.perf_counter() - started


def make_cohort(root: Path, studies: int) -> float:
    """Acquire the cohort's studies under ``root``; returns the wall seconds."""
    started = time.perf_counter()
    cluster = batch.local_cluster(2)
    try:
        with Client(cluster) as client:
            seeds = list(range(1, studies + 1))
            paths = [root / f"knee-{seed:03d}" for seed in seeds]
            n = len(seeds)
            futures = client.map(
                batch.simulate_study, paths, [CONFIGS] * n, [batch.TINY] * n, seeds, pure=False
            )
            client.gather(futures)
    finally:
        cluster.close()
    return time.perf_counter() - started


def timed_run(acquired: Path, dst: Path, workers: int, options: batch.TaskOptions) -> dict:
    """One ``batch all`` over hard-linked copies of the acquired studies on W workers."""
    studies = []
    for src in sorted(acquired.iterdir()):
        shutil.copytree(src, dst / src.name, copy_function=os.link)
        studies.append(dst / src.name)
    started = time.perf_counter()
    cluster = batch.local_cluster(workers)
    try:
        with Client(cluster) as client:
            client.wait_for_workers(workers)
            start_s = time.perf_counter() - started
            warm_s = warm(client, studies[0], dst / "warm", batch.TaskOptions(settings=LIGHT))
            load = os.getloadavg()[0]
            samples: list[float] = []
            done = threading.Event()

            def sample() -> None:
                while not done.wait(LOAD_SAMPLE_S):
                    samples.append(os.getloadavg()[0])

            sampler = threading.Thread(target=sample, daemon=True)
            sampler.start()
            report = batch.run(client, studies, "all", options)
            done.set()
            sampler.join()
    finally:
        cluster.close()
    tasks: dict[str, list[float]] = {}
    for outcome in report.outcomes:
        tasks.setdefault(outcome.task, []).append(outcome.seconds)
    return {
        "workers": workers,
        "wall_s": round(report.seconds, 2),
        "s_per_study": round(report.seconds / len(studies), 2),
        "cluster_start_s": round(start_s, 2),
        "warm_s": round(warm_s, 2),
        "load_avg_1min_before": round(load, 2),
        "load_avg_1min_during": round(sum(samples) / len(samples), 2) if samples else None,
        "failed": sorted(report.failures()),
        "task_s_mean": {t: round(sum(v) / len(v), 2) for t, v in tasks.items()},
        "studies": studies,
    }


def projection(t_study: float, b_study: int, efficiency: float, workers: int) -> dict:
    """Projected wall time of PROJECTED_STUDIES studies on N machines (module docstring)."""
    rows = []
    e = min(max(efficiency, 0.05), 1.0)
    for n in MACHINES:
        compute = math.ceil(PROJECTED_STUDIES / (n * workers)) * (
            t_study / e + b_study / (LINK_BYTES_S / workers)
        )
        storage = PROJECTED_STUDIES * b_study / STORAGE_BYTES_S
        wall = max(compute, storage)
        rows.append(
            {
                "machines": n,
                "workers_per_machine": workers,
                "studies": PROJECTED_STUDIES,
                "wall_s": round(wall, 1),
                "s_per_study": round(wall / PROJECTED_STUDIES, 2),
                "bound": "compute" if compute >= storage else "storage",
            }
        )
    return {
        "formula": "wall = max(ceil(S/(N*W)) * (t_study/e + b_study/(link/W)), S*b_study/storage)",
        "t_study_s": round(t_study, 2),
        "b_study_bytes": b_study,
        "e": round(e, 3),
        "link_bytes_s": LINK_BYTES_S,
        "storage_bytes_s": STORAGE_BYTES_S,
        "rows": rows,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--studies", type=int, default=4, help="cohort size (even: balanced)")
    parser.add_argument("--light", action="store_true", help="the tests' registration settings")
    parser.add_argument("--keep", type=Path, help="make the studies here and keep them")
    args = parser.parse_args()
    if args.studies < 2:
        parser.error("--studies must be at least 2")
    settings = LIGHT if args.light else batch.load_settings(CONFIGS / "registration.yaml")
    options = batch.TaskOptions(settings=settings)
    with tempfile.TemporaryDirectory(prefix="cohort-bench-") as tmp:
        root = args.keep or Path(tmp)
        acquired = root / "acquired"
        acquired.mkdir(parents=True)
        say(f"acquiring {args.studies} studies at study.batch.TINY on 2 workers")
        acquisition_s = make_cohort(acquired, args.studies)
        runs = {}
        for workers in (1, 2):
            say(f"batch all on {workers} worker(s)")
            runs[workers] = timed_run(acquired, root / f"run-{workers}", workers, options)
            say(f"  {runs[workers]['wall_s']} s")
        example = runs[1]["studies"][0]
        read = size_of(example, READ)
        written = size_of(example, WRITTEN) + (example / "study.json").stat().st_size
        read_back = size_of(example, READ_BACK)
        folder = size_of(example, tuple(p.name for p in example.iterdir()))
        t_study = sum(runs[1]["task_s_mean"].values())
        efficiency = runs[1]["wall_s"] / (2 * runs[2]["wall_s"])
        result = {
            "studies": args.studies,
            "workers": 2,
            "wall_s": runs[2]["wall_s"],
            "s_per_study": runs[2]["s_per_study"],
            "wall_s_1_worker": runs[1]["wall_s"],
            "s_per_study_1_worker": runs[1]["s_per_study"],
            "scaling_efficiency_1_to_2": round(efficiency, 3),
            "target_efficiency": 0.8,
            "cpu_count": os.cpu_count(),
            "size": batch.TINY,
            "registration": "light" if args.light else "configs/registration.yaml",
            "acquisition_s": round(acquisition_s, 1),
            "runs": [{k: v for k, v in r.items() if k != "studies"} for r in runs.values()],
            "task_s_mean_1_worker": runs[1]["task_s_mean"],
            "bytes_read_per_study": read,
            "bytes_written_per_study": written,
            "bytes_read_back_per_study": read_back,
            "study_folder_bytes": folder,
            "projection": projection(t_study, read + written + read_back, efficiency, 2),
        }
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()

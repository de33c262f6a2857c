"""``cbct batch``: the derived stages of many studies as tasks on dask.distributed.

A task runs one study's stages with the same functions as ``cbct demo`` (``study.stages``):

========  ===============================  =====================================
task      stages                           reads (checked against study.json)
========  ===============================  =====================================
recon     recon, segmentation              scan/, calibration/ (when complete)
register  registration                     recon/, segmentation/, fluoro/
assess    assessment                       segmentation/, registration/
========  ===============================  =====================================

``all`` chains the three per study (a study's tasks depend on each other, so they never run
at the same time; different studies run in parallel). A task is idempotent: a complete stage
whose files still match their sha256 is skipped, one whose files do not is an error (a study is
never rewritten), and so is an input whose files no longer match. A task that fails is
reported for its study (later tasks of that study are not run); the other studies go on.
A worker that dies mid-task loses nothing: its stage was never marked complete, dask reruns
the task elsewhere (up to ``distributed.scheduler.allowed-failures`` times) and the stage
starts again (``derived_folder`` discards the stale ``<stage>.partial/``).

Every task reads and writes the study folder by path, so the workers must see the studies at
the same (absolute) paths: one machine, or shared storage mounted alike on every machine.
At the end :func:`write_cohort` writes one table with a row per study and bone
(``cohort.csv``, ``cohort.parquet``) and ``cohort.html`` with the cohort plots.
"""

from __future__ import annotations

import base64
import datetime as dt
import glob
import html
import importlib.util
import io
import json
import logging
import math
import os
import time
import uuid
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import dask
import numpy as np
import pyarrow as pa
import pyarrow.csv as pa_csv
import pyarrow.parquet as pq
from distributed import Client, Future, LocalCluster, as_completed, get_worker
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from recon.config import load_config
from registration.labels import BONE_UNITS
from registration.settings import Settings
from scanner.study_folder import Study, StudyError
from study.stages import (
    assessment_stage,
    recon_stage,
    registration_stage,
    segmentation_stage,
)

ACTIONS: dict[str, tuple[str, ...]] = {
    "recon": ("recon",),
    "register": ("register",),
    "assess": ("assess",),
    "all": ("recon", "register", "assess"),
}
"""``cbct batch ACTION``: the tasks each study gets, in order."""
TASK_STAGES: dict[str, tuple[str, ...]] = {
    "recon": ("recon", "segmentation"),
    "register": ("registration",),
    "assess": ("assessment",),
}
"""The study stages each task runs, in order."""
TASK_INPUTS: dict[str, tuple[str, ...]] = {
    "recon": ("scan", "calibration"),
    "register": ("recon", "segmentation", "fluoro"),
    "assess": ("segmentation", "registration"),
}
"""The stages whose files a task reads (checked when the stage is complete)."""
DEFAULT_VOXEL_MM = 1.0
"""Reconstruction voxel when neither the option nor the study's config gives one, mm."""
CONNECT_TIMEOUT_S = 10.0
"""How long ``--scheduler`` waits for the scheduler (and for a worker on it), s."""
PLOT_SIZE_IN = (5.5, 3.6)
PLOT_DPI = 110
BONES = tuple(BONE_UNITS)
"""The rigid units of the cohort table, one row each per study."""


@dataclass(frozen=True)
class TaskOptions:
    """What every task needs besides its study: recon voxel (None: the study's own, mm),
    registration settings (None: the defaults) and the assessment report's title."""

    voxel_mm: float | None = None
    settings: Settings | None = None
    title: str = "Knee kinematics"


@dataclass(frozen=True)
class TaskResult:
    """What a finished task returns: the stages it ran and skipped, its wall time (s) and
    where it ran (worker address, process id)."""

    study: str
    task: str
    ran: tuple[str, ...]
    skipped: tuple[str, ...]
    seconds: float
    worker: str
    pid: int


@dataclass(frozen=True)
class Outcome:
    """One task of one study as the batch saw it: ``ran`` (did work), ``skipped`` (all its
    stages were complete), ``failed`` (with the error) or ``blocked`` (an earlier task of the
    study failed)."""

    study: str
    task: str
    status: str
    error: str = ""
    seconds: float = math.nan
    worker: str = ""
    pid: int = 0


@dataclass
class BatchReport:
    """Every outcome of a batch run and its wall time, s."""

    outcomes: list[Outcome] = field(default_factory=list)
    seconds: float = 0.0

    def failures(self) -> dict[str, Outcome]:
        """Study path -> its failed task."""
        return {o.study: o for o in self.outcomes if o.status == "failed"}


# -- inputs -------------------------------------------------------------------------------------


def find_studies(patterns: Iterable[str]) -> list[Path]:
    """The study folders the patterns name (globs, ``**`` recursive), absolute, sorted, once
    each. Raises StudyError for a pattern that matches nothing or a match that is not a
    study (nothing is written)."""
    found: dict[Path, None] = {}
    for pattern in patterns:
        matches = sorted(glob.glob(os.path.expanduser(pattern), recursive=True))
        if not matches:
            raise StudyError(f"{pattern!r} matches nothing")
        for match in matches:
            path = Path(match).resolve()
            Study.open(path)  # raises StudyError, naming the folder, for a non-study
            found[path] = None
    return sorted(found)


def new_output_folder(out: Path | None) -> Path:
    """The cohort output folder: ``out`` or ``cohort-<UTC time>``; must not exist or be
    empty. Checked before any work, created only when the cohort is written."""
    if out is None:
        out = Path(f"cohort-{dt.datetime.now(dt.UTC):%Y%m%d-%H%M%S}")
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise StudyError(f"{out} exists and is not empty: choose a new --out (never overwritten)")
    return out.resolve()


# -- the cluster --------------------------------------------------------------------------------


def local_cluster(workers: int, dashboard_address: str = ":0") -> LocalCluster:
    """A LocalCluster of ``workers`` single-threaded worker processes under nannies (a dead
    worker is restarted). Numba in each worker uses one thread: the parallelism is the
    workers'; more threads per process on as many cores only oversubscribe them."""
    if workers < 1:
        raise ValueError(f"--workers must be at least 1, got {workers}")
    with dask.config.set({"distributed.nanny.pre-spawn-environ.NUMBA_NUM_THREADS": "1"}):
        return LocalCluster(
            n_workers=workers,
            threads_per_worker=1,
            processes=True,
            dashboard_address=dashboard_address,
            silence_logs=logging.CRITICAL,  # failures are reported per study by run()
        )


def connect(address: str, timeout_s: float = CONNECT_TIMEOUT_S) -> Client:
    """A client of the scheduler at ``address`` with at least one worker, or StudyError within
    about ``timeout_s`` (twice: connect, then wait for a worker)."""
    try:
        client = Client(address, timeout=f"{timeout_s}s")
    except (OSError, TimeoutError, ValueError) as err:
        raise StudyError(
            f"no dask scheduler reachable at {address!r} within {timeout_s:g} s: {err}"
        ) from err
    try:
        client.wait_for_workers(1, timeout=timeout_s)
    except (OSError, TimeoutError) as err:
        client.close()
        raise StudyError(f"the scheduler at {address} has no worker after {timeout_s:g} s") from err
    return client


def open_client(
    scheduler: str | None, workers: int, timeout_s: float = CONNECT_TIMEOUT_S
) -> tuple[Client, LocalCluster | None]:
    """A client of the scheduler at ``scheduler`` (see :func:`connect`), or of a new
    :func:`local_cluster` of ``workers`` processes when it is None; and that cluster."""
    if scheduler is not None:
        return connect(scheduler, timeout_s), None
    cluster = local_cluster(workers)
    return Client(cluster), cluster


def _scheduler_has_bokeh() -> bool:
    return importlib.util.find_spec("bokeh") is not None


def dashboard(client: Client) -> str | None:
    """The Dask dashboard's address, None when the scheduler serves none (its dashboard needs
    bokeh, which this project does not require)."""
    try:
        services = client.scheduler_info().get("services", {})
        if "dashboard" not in services or not client.run_on_scheduler(_scheduler_has_bokeh):
            return None
    except (OSError, TimeoutError):
        return None
    return client.dashboard_link


# -- the task ------------------------------------------------------------------------------------


def load_settings(path: Path) -> Settings:
    """Registration settings from a YAML file (``configs/registration.yaml``)."""
    return load_config(path, Settings)


def recon_voxel_mm(study: Study) -> float:
    """The recon voxel a simulated study was made for (its demo/cohort size), mm."""
    for kind in ("cohort", "demo"):
        size = study.manifest["config"].get(kind, {}).get("size", {})
        if "recon_voxel_mm" in size:
            return float(size["recon_voxel_mm"])
    return DEFAULT_VOXEL_MM


def _changed(study: Study, stage: str) -> list[str]:
    """Files of a stage (its folder) that no longer match their recorded sha256."""
    return study.verify(f"{stage}/")


def run_task(
    path: str, task: str, options: TaskOptions, after: TaskResult | None = None
) -> TaskResult:
    """Run one task of one study (module docstring); ``after`` is the study's previous task
    (only a dependency). Raises StudyError for a study it must not touch, or what the stage
    raised (the stage is then marked incomplete with the reason)."""
    started = time.perf_counter()
    study = Study.open(path)
    todo = []
    for stage in TASK_STAGES[task]:
        if study.stage(stage).get("status") == "complete":
            bad = _changed(study, stage)
            if bad:
                raise StudyError(
                    f"{stage} is complete but {len(bad)} of its files no longer match their "
                    f"sha256 in study.json ({', '.join(bad[:3])}): a study is never rewritten; "
                    "restore them, or remove the stage to redo it"
                )
        else:
            todo.append(stage)
    if todo:
        for stage in TASK_INPUTS[task]:
            if study.stage(stage).get("status") == "complete":
                bad = _changed(study, stage)
                if bad:
                    reason = (
                        f"input {stage}/ is damaged: {', '.join(bad[:3])} missing or no longer "
                        "matching its sha256 in study.json"
                    )
                    study.mark(todo[0], "incomplete", reason=f"StudyError: {reason}")
                    raise StudyError(reason)

    def quiet(_message: str) -> None:
        pass

    ran: list[str] = []
    if task == "recon":
        voxel = options.voxel_mm or recon_voxel_mm(study)
        if recon_stage(study, voxel, None, quiet):
            ran.append("recon")
        if segmentation_stage(study, quiet):
            ran.append("segmentation")
    elif task == "register":
        if registration_stage(study, options.settings, quiet):
            ran.append("registration")
    elif task == "assess":
        if assessment_stage(study, f"{options.title}: {study.path.name}", quiet):
            ran.append("assessment")
    else:
        raise ValueError(f"unknown task {task!r}; tasks are {tuple(TASK_STAGES)}")
    try:
        worker = get_worker().address
    except ValueError:  # called outside a worker (tests, debugging)
        worker = ""
    return TaskResult(
        path,
        task,
        tuple(ran),
        tuple(s for s in TASK_STAGES[task] if s not in ran),
        round(time.perf_counter() - started, 3),
        worker,
        os.getpid(),
    )


# -- the batch -----------------------------------------------------------------------------------


def submit(
    client: Client, studies: Sequence[Path], action: str, options: TaskOptions
) -> dict[Future, tuple[str, str, Future | None]]:
    """Submit every study's tasks; future -> (study, task, the study's previous future)."""
    if action not in ACTIONS:
        raise ValueError(f"unknown action {action!r}; actions are {tuple(ACTIONS)}")
    token = uuid.uuid4().hex[:8]
    futures: dict[Future, tuple[str, str, Future | None]] = {}
    for i, path in enumerate(studies):
        previous: Future | None = None
        for task in ACTIONS[action]:
            future = client.submit(
                run_task,
                str(path),
                task,
                options,
                previous,
                key=f"{task}-{token}-{i:04d}",
                pure=False,
                retries=0,
            )
            futures[future] = (str(path), task, previous)
            previous = future
    return futures


def run(
    client: Client,
    studies: Sequence[Path],
    action: str,
    options: TaskOptions,
    on_outcome: Callable[[Outcome], None] | None = None,
) -> BatchReport:
    """Run ``action`` on every study on ``client``'s cluster; ``on_outcome`` hears of each
    task as it finishes. A failed task fails its study only."""
    started = time.perf_counter()
    futures = submit(client, studies, action, options)
    report = BatchReport()
    failed: set[str] = set()
    try:
        for future in as_completed(list(futures)):
            study, task, previous = futures[future]
            if future.status == "finished":
                result: TaskResult = future.result()
                status = "ran" if result.ran else "skipped"
                outcome = Outcome(
                    study, task, status, "", result.seconds, result.worker, result.pid
                )
            elif study in failed or (previous is not None and previous.status == "error"):
                # the error of an earlier task of the study, passed on by dask
                outcome = Outcome(study, task, "blocked", "an earlier task failed")
            else:
                failed.add(study)
                outcome = Outcome(study, task, "failed", _error(future))
            report.outcomes.append(outcome)
            if on_outcome is not None:
                on_outcome(outcome)
    except BaseException:
        client.cancel(list(futures))
        raise
    rank = {str(path): i for i, path in enumerate(studies)}
    report.outcomes.sort(key=lambda o: (rank[o.study], ACTIONS[action].index(o.task)))
    report.seconds = round(time.perf_counter() - started, 3)
    return report


def _error(future: Future) -> str:
    """A failed (or cancelled) future's error in words."""
    if future.status == "cancelled":
        return "cancelled: the scheduler dropped the task (was it restarted?)"
    err = future.exception()
    return f"{type(err).__name__}: {err}"


# -- the cohort ----------------------------------------------------------------------------------

COLUMNS = pa.schema(
    [
        ("study", pa.string()),
        ("path", pa.string()),
        ("status", pa.string()),
        ("failed_task", pa.string()),
        ("error", pa.string()),
        ("bone", pa.string()),
        ("tre_mm_mean", pa.float64()),
        ("tre_mm_max", pa.float64()),
        ("ncc_mean", pa.float64()),
        ("ncc_min", pa.float64()),
        ("failed_frames", pa.int64()),
        ("registration_s", pa.float64()),
        ("dice", pa.float64()),
        ("recon_s", pa.float64()),
        ("segmentation_s", pa.float64()),
        ("registration_stage_s", pa.float64()),
        ("assessment_s", pa.float64()),
        ("frames", pa.int64()),
        ("measured_frames", pa.int64()),
        ("max_abs_mld_mm", pa.float64()),
        ("ddv_mm2", pa.float64()),
        ("flexion_range_deg", pa.float64()),
        ("flagged_frames", pa.int64()),
    ]
)
"""The cohort table: one row per study and bone. TRE (per bone, over frames, mm) where the
study has ground truth; similarity = the registration's NCC; ``registration_s`` the bone's
registration seconds summed over frames; ``*_s`` the study's stage seconds; the assessment's
headline metrics (frames measured, max |MLD| mm, DDV mm^2, flexion range deg: over the measured
frames) repeat on each bone's row."""


def _body(row: dict) -> str:
    """The body a per-frame row of registration.json or metrics.json is of (``body``; studies
    registered before the key was named so have ``bone``)."""
    return row["body"] if "body" in row else row["bone"]


def _json(path: Path) -> dict:
    return json.loads(path.read_text(encoding="utf-8")) if path.is_file() else {}


def cohort_rows(studies: Sequence[Path], report: BatchReport | None = None) -> list[dict]:
    """The cohort table's rows (:data:`COLUMNS`) from the study folders and the run."""
    failures = report.failures() if report is not None else {}
    rows = []
    for path in studies:
        study = Study.open(path)
        stages = study.manifest["stages"]
        registration = _json(path / "registration" / "registration.json").get("frames", [])
        truth = _json(path / "registration" / "metrics.json").get("per_frame", [])
        dice = stages.get("segmentation", {}).get("dice", {})
        assessment = stages.get("assessment", {})
        failure = failures.get(str(path))
        for bone in BONES:
            tre = [r["tre_mm"] for r in truth if _body(r) == bone]
            reg = [r for r in registration if _body(r) == bone]
            ncc = [r["ncc"] for r in reg if r["ncc"] is not None and math.isfinite(r["ncc"])]
            rows.append(
                {
                    "study": path.name,
                    "path": str(path),
                    "status": "failed" if failure else "ok",
                    "failed_task": failure.task if failure else None,
                    "error": failure.error if failure else None,
                    "bone": bone,
                    "tre_mm_mean": float(np.mean(tre)) if tre else None,
                    "tre_mm_max": float(np.max(tre)) if tre else None,
                    "ncc_mean": float(np.mean(ncc)) if ncc else None,
                    "ncc_min": float(np.min(ncc)) if ncc else None,
                    "failed_frames": sum(bool(r["failed"]) for r in reg) if reg else None,
                    "registration_s": float(sum(r["seconds"] for r in reg)) if reg else None,
                    "dice": dice.get(bone),
                    "recon_s": _seconds(stages, "recon"),
                    "segmentation_s": _seconds(stages, "segmentation"),
                    "registration_stage_s": _seconds(stages, "registration"),
                    "assessment_s": _seconds(stages, "assessment"),
                    "frames": assessment.get("frames"),
                    "measured_frames": assessment.get("measured_frames"),
                    "max_abs_mld_mm": assessment.get("max_abs_mld_mm"),
                    "ddv_mm2": assessment.get("ddv_mm2"),
                    "flexion_range_deg": assessment.get("flexion_range_deg"),
                    "flagged_frames": (
                        len(assessment["flagged_frames"])
                        if "flagged_frames" in assessment
                        else None
                    ),
                }
            )
    return rows


def _seconds(stages: dict, name: str) -> float | None:
    stage = stages.get(name, {})
    return stage.get("seconds") if stage.get("status") == "complete" else None


@dataclass(frozen=True)
class CohortFiles:
    """The files :func:`write_cohort` wrote."""

    csv: Path
    parquet: Path
    html: Path
    plots: tuple[Path, ...]


def write_cohort(
    out: Path, studies: Sequence[Path], report: BatchReport | None = None, action: str = "all"
) -> CohortFiles:
    """Write ``cohort.csv``, ``cohort.parquet``, the plots and ``cohort.html`` into the new
    folder ``out`` (refused when it exists and is not empty)."""
    out = new_output_folder(out)
    rows = cohort_rows(studies, report)
    table = pa.Table.from_pylist(rows, schema=COLUMNS)
    out.mkdir(parents=True, exist_ok=True)
    pa_csv.write_csv(table, out / "cohort.csv")
    pq.write_table(table, out / "cohort.parquet")
    per_study = {r["path"]: r for r in rows}  # study-level columns repeat on every bone row
    plots = _plots(list(per_study.values()), out)
    page = _page(rows, list(per_study.values()), plots, report, action)
    (out / "cohort.html").write_text(page, encoding="utf-8")
    return CohortFiles(out / "cohort.csv", out / "cohort.parquet", out / "cohort.html", plots)


def _plots(studies: list[dict], out: Path) -> tuple[Path, ...]:
    """Distribution of max |MLD| and flexion range vs max |MLD|, one point per assessed study
    (PNG beside the page)."""
    done = [s for s in studies if s["max_abs_mld_mm"] is not None]
    mld = np.array([s["max_abs_mld_mm"] for s in done], dtype=float)
    flexion = np.array([s["flexion_range_deg"] for s in done], dtype=float)

    fig = Figure(figsize=PLOT_SIZE_IN, layout="constrained")
    ax = fig.add_subplot()
    if done:
        ax.hist(mld, bins=max(3, min(20, len(done))), color="tab:blue", edgecolor="white")
        ax.yaxis.set_major_locator(MaxNLocator(integer=True))
        median = float(np.median(mld))
        ax.axvline(median, color="k", ls="--", label=f"median {median:.2f} mm")
        ax.legend()
    else:
        ax.text(0.5, 0.5, "no assessed study", ha="center", transform=ax.transAxes)
    ax.set(xlabel="max |MLD| (mm)", ylabel="studies", title=f"max |MLD|, {len(done)} studies")
    first = out / "mld_max_distribution.png"
    fig.savefig(first, format="png", dpi=PLOT_DPI)

    fig = Figure(figsize=PLOT_SIZE_IN, layout="constrained")
    ax = fig.add_subplot()
    if done:
        ax.scatter(flexion, mld, color="tab:orange")
        for s, x, y in zip(done, flexion, mld, strict=True):
            ax.annotate(s["study"], (x, y), fontsize=7, xytext=(3, 3), textcoords="offset points")
    else:
        ax.text(0.5, 0.5, "no assessed study", ha="center", transform=ax.transAxes)
    ax.set(
        xlabel="flexion range (deg)", ylabel="max |MLD| (mm)", title="flexion range vs max |MLD|"
    )
    second = out / "flexion_vs_mld.png"
    fig.savefig(second, format="png", dpi=PLOT_DPI)
    return first, second


def _cell(value: object) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "–"
    if isinstance(value, float):
        return f"{value:.3g}"
    return html.escape(str(value))


def _page(
    rows: list[dict],
    studies: list[dict],
    plots: Sequence[Path],
    report: BatchReport | None,
    action: str,
) -> str:
    """The cohort HTML page: per-study summary, failures, plots (embedded), per-bone table."""
    study_cols = (
        "study",
        "status",
        "failed_task",
        "measured_frames",
        "max_abs_mld_mm",
        "ddv_mm2",
        "flexion_range_deg",
        "flagged_frames",
        "recon_s",
        "registration_stage_s",
    )
    bone_cols = ("study", "bone", "tre_mm_mean", "tre_mm_max", "ncc_mean", "dice", "registration_s")

    def table(items: list[dict], cols: Sequence[str]) -> str:
        head = "".join(f"<th>{c}</th>" for c in cols)
        body = "".join(
            "<tr>" + "".join(f"<td>{_cell(item[c])}</td>" for c in cols) + "</tr>" for item in items
        )
        return f"<table><tr>{head}</tr>{body}</table>"

    images = "".join(
        f'<figure><img alt="{p.stem}" src="data:image/png;base64,'
        f'{base64.b64encode(p.read_bytes()).decode()}"><figcaption>{p.name}</figcaption></figure>'
        for p in plots
    )
    failed = [s for s in studies if s["status"] == "failed"]
    failures = (
        "<ul>"
        + "".join(
            f"<li><b>{html.escape(s['study'])}</b> ({html.escape(s['path'])}), task "
            f"{html.escape(s['failed_task'])}: {html.escape(s['error'])}</li>"
            for s in failed
        )
        + "</ul>"
        if failed
        else "<p>none</p>"
    )
    wall = f", {report.seconds:.1f} s wall" if report is not None else ""
    when = dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
    buf = io.StringIO()
    buf.write(
        "<!doctype html><html><head><meta charset='utf-8'><title>cohort</title><style>"
        "body{font-family:sans-serif;margin:2em}table{border-collapse:collapse;margin:1em 0}"
        "td,th{border:1px solid #ccc;padding:3px 8px;text-align:right}"
        "figure{display:inline-block;margin:0 1em}</style></head><body>"
    )
    buf.write(
        f"<h1>Cohort: {len(studies)} studies</h1><p>cbct batch {html.escape(action)}, "
        f"{when}{wall}; {len(failed)} failed. Units: mm, mm², degrees, seconds.</p>"
    )
    buf.write(f"<h2>Failures</h2>{failures}<h2>Plots</h2>{images}")
    buf.write(f"<h2>Studies</h2>{table(studies, study_cols)}")
    buf.write(f"<h2>Bones</h2>{table(rows, bone_cols)}</body></html>")
    return buf.getvalue()


# -- making cohorts (simulation) ---------------------------------------------------------------

TINY: dict[str, float | int] = {
    "views": 60,
    "panel": 256,
    "calibration_panel": 512,
    "phantom_voxel_mm": 1.0,
    "recon_voxel_mm": 1.0,
    "fluoro_panel": 128,
    "fluoro_voxel_mm": 1.5,
    "frames": 3,
    "max_flexion_deg": 20.0,
}
"""A study size (keys of ``study.demo.QUICK``) for tests and benchmarks: about 17 s of
acquisition and 10-30 s of derived stages per study on one core. Smaller breaks a stage: the
calibration needs 1.2 mm pixels (panel 512) to find the steel balls, and segmentation loses
the patella with a 128 panel or 1.5 mm voxels."""


def simulate_study(
    path: str | Path, configs: Path, size: dict, seed: int, varus_deg: float | None = None
) -> str:
    """A new simulated study at ``path``: the demo's acquisitions (``study.demo.acquire``)
    with ``seed``, recorded under ``cohort`` in study.json, its reconstruction left to the
    batch. Returns the path."""
    from study import demo

    varus = demo.VARUS_DEG if varus_deg is None else varus_deg
    study = Study.create(path, {"cohort": {"size": size, "seed": seed, "varus_deg": varus}})
    demo.acquire(study, configs, size, seed=seed, varus_deg=varus, live_recon=False)
    return str(path)


def outcome_rows(report: BatchReport) -> list[dict]:
    """The outcomes as plain dicts (for JSON)."""
    return [asdict(o) for o in report.outcomes]

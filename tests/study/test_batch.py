"""``cbct batch`` on loopback: LocalClusters of 2 worker processes over simulated studies.

The slow test's cohort (knee-1, a tiny simulated study, and knee-3: a copy of it whose
fluoroscopy frames a failing disk truncated after acquisition); the default suite's worker
kill works on a copy of the quick demo's study (tests/study/conftest.py). Each test works on
hard-linked copies (study files are never rewritten in place, only replaced by rename, so the
copies stay independent).
"""

from __future__ import annotations

import os
import shutil
import socket
import time
from pathlib import Path

import pyarrow.csv as pa_csv
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from configs import CONFIGS
from scanner.study_folder import Study
from study import batch
from study.cli import app

runner = CliRunner()

TINY = batch.TINY
LIGHT_REGISTRATION = """\
pyramid_mm: [2.4]
de_popsize: 5
de_maxiter: 5
powell_maxfev: 60
nelder_mead_maxfev: 20
passes: 1
drop_ncc: 1.0
"""
SEEDS = (1,)
FAULTY = "knee-3"
NAMES = (*(f"knee-{seed}" for seed in SEEDS), FAULTY)
DERIVED = ("recon", "segmentation", "registration", "assessment")


@pytest.fixture(scope="module")
def cohort(tmp_path_factory) -> Path:
    """An acquired study (seed 1, simulated in this process: the cluster is under test below)
    and knee-3: a copy of it with its frames corrupted."""
    root = tmp_path_factory.mktemp("cohort")
    paths = [
        Path(batch.simulate_study(root / f"knee-{seed}", CONFIGS, TINY, seed)) for seed in SEEDS
    ]
    shutil.copytree(paths[0], root / FAULTY, copy_function=os.link)
    frames = root / FAULTY / "fluoro" / "frames.mha"
    damaged = frames.with_name("damaged.tmp")
    damaged.write_bytes(frames.read_bytes()[: frames.stat().st_size // 2])
    os.replace(damaged, frames)  # a new inode: a truncated copy, as a failing disk leaves it
    (root / "settings.yaml").write_text(LIGHT_REGISTRATION, encoding="utf-8")
    return root


def copy_cohort(cohort: Path, dst: Path, names: tuple[str, ...] | None = None) -> list[Path]:
    """Hard-linked copies of the cohort's studies under ``dst``."""
    names = names or NAMES
    for name in names:
        shutil.copytree(cohort / name, dst / name, copy_function=os.link)
    return [dst / name for name in names]


def stage_times(path: Path) -> dict[str, str]:
    return {s: Study.open(path).stage(s).get("updated", "") for s in DERIVED}


@pytest.mark.slow
def test_batch_all_makes_the_cohort_reports_the_fault_and_skips_finished_work(cohort, tmp_path):
    """Every stage of both studies on 2 workers (about 30 s on 2 cores; the default suite's
    small version: a worker killed mid-task, below, and the refusals of bad input)."""
    studies = copy_cohort(cohort, tmp_path / "studies")
    settings = str(cohort / "settings.yaml")
    args = ["batch", "all", str(tmp_path / "studies" / "knee-*"), "--workers", "2"]
    first = runner.invoke(app, [*args, "--out", str(tmp_path / "first"), "--settings", settings])
    assert first.exit_code == 1, first.output
    assert "local cluster of 2 worker process(es)" in first.output
    assert "1 of 2 studies failed" in first.output
    assert f"{FAULTY}: register: StudyError: input fluoro/ is damaged" in first.output
    assert "fluoro/frames.mha" in first.output

    for path in studies:
        study = Study.open(path)
        assert study.verify() == [] or path.name == FAULTY
        done = [s for s in DERIVED if study.stage(s).get("status") == "complete"]
        if path.name == FAULTY:  # reconstructed and segmented; never registered
            assert done == ["recon", "segmentation"]
            assert "fluoro/ is damaged" in study.stage("registration")["reason"]
            assert study.verify() == ["fluoro/frames.mha"]
        else:
            assert done == list(DERIVED)
        assert not list(path.glob("*.partial"))

    table = pq.read_table(tmp_path / "first" / "cohort.parquet").to_pylist()
    assert len(table) == len(NAMES) * len(batch.BONES)
    assert pa_csv.read_csv(tmp_path / "first" / "cohort.csv").num_rows == len(table)
    for row in table:
        if row["study"] == FAULTY:
            assert row["status"] == "failed" and row["failed_task"] == "register"
            assert "frames.mha" in row["error"] and row["max_abs_mld_mm"] is None
            assert row["recon_s"] > 0 and row["tre_mm_mean"] is None
        else:
            assert row["status"] == "ok" and row["error"] is None
            for key in ("tre_mm_mean", "ncc_mean", "registration_s", "max_abs_mld_mm"):
                assert row[key] is not None and row[key] >= 0, key
            assert row["flexion_range_deg"] is not None and row["frames"] == TINY["frames"]
    page = (tmp_path / "first" / "cohort.html").read_text(encoding="utf-8")
    assert page.count("data:image/png;base64,") == 2 and FAULTY in page
    assert (tmp_path / "first" / "flexion_vs_mld.png").is_file()

    before = {p.name: stage_times(p) for p in studies}
    second = runner.invoke(app, [*args, "--out", str(tmp_path / "second"), "--settings", settings])
    assert second.exit_code == 1, second.output
    assert "1 of 2 studies failed" in second.output and "skipped" in second.output
    after = {p.name: stage_times(p) for p in studies}
    faulty_before, faulty_after = before.pop(FAULTY), after.pop(FAULTY)
    assert after == before  # nothing redone
    assert faulty_after["recon"] == faulty_before["recon"]  # only its registration tried again
    assert Study.open(tmp_path / "studies" / FAULTY).stage("registration")["status"] == "incomplete"
    again = pq.read_table(tmp_path / "second" / "cohort.parquet").to_pylist()
    assert [r["max_abs_mld_mm"] for r in again] == [r["max_abs_mld_mm"] for r in table]

    taken = runner.invoke(app, [*args, "--out", str(tmp_path / "second")])
    assert taken.exit_code == 2 and "exists and is not empty" in taken.output


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_bad_input_is_refused_and_nothing_is_written(tmp_path):
    out = tmp_path / "cohort"
    nothing = runner.invoke(app, ["batch", "all", str(tmp_path / "no-such-*"), "--out", str(out)])
    assert nothing.exit_code == 2 and "matches nothing" in nothing.output
    (tmp_path / "not-a-study").mkdir()
    stray = runner.invoke(app, ["batch", "recon", str(tmp_path / "not-a-study"), "--out", str(out)])
    assert stray.exit_code == 2 and "is not a study folder" in stray.output
    study = tmp_path / "study"
    Study.create(study, {})
    unknown = runner.invoke(app, ["batch", "segment", str(study), "--out", str(out)])
    assert unknown.exit_code == 2 and "unknown action" in unknown.output

    started = time.monotonic()
    address = f"tcp://127.0.0.1:{_free_port()}"
    args = ["batch", "all", str(study), "--scheduler", address, "--timeout", "2", "--out", str(out)]
    unreachable = runner.invoke(app, args)
    assert unreachable.exit_code == 2, unreachable.output
    assert f"no dask scheduler reachable at '{address}' within 2 s" in unreachable.output
    assert time.monotonic() - started < 15
    assert not out.exists()
    assert sorted(p.name for p in study.iterdir()) == ["study.json"]


def test_per_frame_rows_read_by_body_and_by_the_older_bone_key() -> None:
    assert batch._body({"body": "femur", "ncc": 0.9}) == "femur"
    assert batch._body({"bone": "patella", "ncc": 0.9}) == "patella"  # registered before

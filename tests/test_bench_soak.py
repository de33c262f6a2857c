"""bench/soak.py in small: scans with random faults (process kills and a full disk included),
each resumed until complete, checked against the soak's targets."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def load_soak():
    spec = importlib.util.spec_from_file_location("bench_soak", ROOT / "bench" / "soak.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def check(result: dict, scans: int) -> None:
    """The soak's targets: every scan complete, nothing lost, no pulse after a fault."""
    assert result["faults"] >= scans, result
    assert result["scans_complete"] == scans, result
    assert result["views_lost"] == 0 and result["corrupt_files"] == 0, result
    assert result["x_ray_on_after_fault"] == 0 and result["hangs"] == 0, result
    assert result["exp_after_stop"] == 0, result
    assert result["faults_over_bound"] == 0 and result["faults_safe_unconfirmed"] == 0, result
    assert result["targets_met"], result


def test_a_scan_killed_while_it_writes_is_resumed_whole(tmp_path):
    """One scan, its process group SIGKILLed while a view's file is written (twice), resumed
    to the end (about 12 s; the device faults and the stop signals have their own tests in
    tests/scanner)."""
    soak = load_soak()
    kinds = ("sigkill",)
    result = soak.soak(
        scans=1, seed=2, views=12, kinds=kinds, work=tmp_path / "soak", backends=("sim",)
    )
    check(result, 1)
    assert result["sigkill_mid_write"] >= 1, result


@pytest.mark.slow
def test_small_soak_meets_its_targets(tmp_path):
    """Two scans, process kills and full disks (about 30 s)."""
    soak = load_soak()
    result = soak.soak(
        scans=2,
        seed=4,
        views=12,
        kinds=("sigkill", "disk_full"),
        work=tmp_path / "soak",
        backends=("sim",),  # the UR backend's stops: tests/scanner/test_stop_signals_scan.py
    )
    check(result, 2)


def test_a_view_reserved_before_its_pulse_is_not_counted_as_stored(tmp_path):
    """The soak (and the stop-signal tests) wait for stored views by counting their records: a
    view's files reserved before its pulse (``Study.reserve``: ``.view_0001.tmp.json``) are
    not one, or a stop meant for after a view lands before the view's exposure."""
    from scanner.study_folder import Study

    soak = load_soak()
    study = Study.create(tmp_path / "study", {})
    (tmp_path / "study" / "scan" / "views").mkdir(parents=True)
    study.write_with_record({}, "scan/views/view_0000.json", lambda _digests: b"{}")
    reservation = study.reserve({"scan/views/view_0001.json": 1024})
    assert any(p.name.endswith(".json") for p in reservation.paths)
    assert soak.count_views(tmp_path / "study") == 1
    reservation.release()

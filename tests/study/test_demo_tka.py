"""``cbct demo --tka --quick`` end to end (slow: 425 s on 2 cores): every stage of the
knee replacement's study complete, each scored against the simulation's truth. Its parts run
by default in their own tests (tests/recon/test_mar.py, tests/sim/test_tka_ct.py,
tests/registration/test_placement.py, tests/registration/test_implants.py)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from study.cli import app
from study.demo import TKA_STAGES

DATA = Path(__file__).resolve().parents[3] / "shared" / "data" / "grand-challenge-tka"
pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not DATA.is_dir(), reason=f"no grand-challenge data at {DATA}"),
]


def test_the_knee_replacement_demo_completes_every_stage(tmp_path: Path) -> None:
    out = tmp_path / "study"
    result = CliRunner().invoke(app, ["demo", "--tka", "--quick", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "demo (knee replacement) finished" in result.output
    stages = json.loads((out / "study.json").read_text())["stages"]
    assert all(stages[name]["status"] == "complete" for name in TKA_STAGES)
    recon = stages["recon"]
    # NMAR removes most of the streaks' error (bench/mar.py: 2.0 -> 1.1 x the metal-free's)
    assert recon["rmse_outside_metal_per_mm"] < 0.6 * recon["rmse_outside_metal_uncorrected_per_mm"]
    for body in ("femur", "tibia"):  # a few tenths at 0.8 mm voxels (tests/registration)
        assert stages["placement"][body]["error_deg"] < 1.5
        assert stages["placement"][body]["error_mm"] < 1.5
    assert stages["segmentation"]["dice_near_metal"]["tibia"] > 0.8
    # 30 frames through the gait (bench/registration.py's tka regime: TRE median about 0.3 mm,
    # RSR 98-100 %; here 0.33 mm and 98.3 %: one of 60 registrations beyond 1.5 mm)
    assert stages["registration"]["tre_mm_median"] < 0.5
    assert stages["registration"]["rsr_pct"] >= 95.0
    # no flag the true poses do not give (they flag frames 23-24 and 28: the lateral condyle
    # 2-5 mm above the insert while the medial bears on it), none from a frame left out
    assessment = stages["assessment"]
    assert set(assessment["flagged_frames"]) <= set(assessment["truth_flagged_frames"])
    with (out / "assessment" / "metrics.csv").open(encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    assert all(r["status"] == "measured" for r in rows if r["flagged"] == "1")

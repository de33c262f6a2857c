"""``cbct scan`` from the console: confirmations, a fault and its resume (the volume
reconstructed during the scan written as the recon stage), refusals."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml
from typer.testing import CliRunner

from configs import CONFIGS
from recon.io import read_volume
from scanner.study_folder import Study
from study.cli import app

runner = CliRunner()


def tiny_protocol(tmp: Path) -> Path:
    """The demo protocol read out 8x8 binned with 60 views: a scan in seconds."""
    data = yaml.safe_load((CONFIGS / "protocols" / "demo_knee.yaml").read_text(encoding="utf-8"))
    data["detector"] = {"rows": 64, "cols": 64, "pixel_pitch_mm": 9.6}
    data["orbit"]["views"] = 60
    path = tmp / "tiny.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def sim_config(tmp: Path, **faults) -> Path:
    path = tmp / f"sim-{len(faults)}.yaml"
    path.write_text(yaml.safe_dump({"faults": faults}))
    return path


def scan(*args: str, answers: str | None = None):
    return runner.invoke(
        app, ["scan", "--phantom-voxel-mm", "2", "--recon-voxel-mm", "4", *args], input=answers
    )


def test_scan_fault_then_resume(tmp_path):
    study = tmp_path / "study"
    common = ["--study", str(study), "--yes"]
    faulty = sim_config(tmp_path, protective_stop_at_view=20)
    result = scan(
        *common, "--protocol", str(tiny_protocol(tmp_path)), "--backend-config", str(faulty)
    )
    assert result.exit_code == 1  # failed during the work (2: input refused)
    assert "protective stop" in result.output and "cbct scan --resume" in result.output
    assert Study.open(study).stage("scan")["views_stored"] == 20

    result = scan(*common, "--resume")  # the study's own config: its fault is not repeated
    assert result.exit_code == 0, result.output
    assert "scan complete: 60 views" in result.output
    assert "reconstructed during the scan" in result.output
    done = Study.open(study)
    assert done.verify() == []
    assert done.stage("recon")["status"] == "complete" and done.stage("recon")["during_scan"]
    assert (study / "recon" / "volume.nii.gz").is_file()
    assert "protective_stop_at_view=20) are not injected again" in result.output

    again = scan(*common, "--resume")  # a script resuming until done learns it is done
    assert again.exit_code == 0 and "scan complete already: 60 views" in again.output


def test_a_planned_study_is_scanned_and_declining_at_the_prompt_moves_nothing(tmp_path):
    study, protocol = tmp_path / "study", tiny_protocol(tmp_path)
    planned = runner.invoke(app, ["plan", "--protocol", str(protocol), "--out", str(study)])
    assert planned.exit_code == 0 and f"cbct scan --study {study}" in planned.output
    result = scan("--study", str(study), "--protocol", str(protocol), answers="n\n")
    assert result.exit_code == 2 and "Start motion?" in result.output
    assert "declined motion" in result.output and "cbct scan --resume" in result.output
    assert not (study / "scan" / "views").exists()
    silent = scan("--study", str(study), "--resume", answers="")  # no terminal, no --yes
    assert silent.exit_code == 2 and "no answer" in silent.output and "--yes" in silent.output
    assert not (study / "scan" / "views").exists()


def test_refusals(tmp_path):
    result = scan("--study", str(tmp_path / "s"), "--yes")
    assert result.exit_code == 2 and "needs --protocol" in result.output
    result = scan(
        "--study",
        str(tmp_path / "s"),
        "--yes",
        "--protocol",
        str(tiny_protocol(tmp_path)),
        "--backend",
        "gantry",
    )
    assert result.exit_code == 2 and "backend must be one of ['sim', 'ur']" in result.output
    assert not (tmp_path / "s").exists()
    result = scan("--study", str(tmp_path / "nothing"), "--yes", "--resume")
    assert result.exit_code == 2 and "not a study folder" in result.output


def test_a_protocol_that_asks_for_tv_gets_it_from_the_scans_fdk(tmp_path):
    """A protocol whose reconstruction is tv: the recon stage iterates from the volume made
    during the scan, records how (method, iterations, weight) and the phantom error of both,
    and the iterations bring the volume closer to the phantom than FDK's."""
    protocol = tiny_protocol(tmp_path)
    data = yaml.safe_load(protocol.read_text(encoding="utf-8"))
    data["reconstruction"] = {"method": "tv", "iterations": 4}
    data["orbit"]["views"] = 40  # under the motion estimate's 60: the stage goes straight on
    protocol.write_text(yaml.safe_dump(data))
    study = tmp_path / "study"
    result = scan("--study", str(study), "--yes", "--protocol", str(protocol))
    assert result.exit_code == 0, result.output
    recon = Study.open(study).stage("recon")
    method = recon["reconstruction"]
    assert method["method"] == "tv" and method["ran"] and 1 <= method["iterations"] <= 4
    assert method["tv_weight_per_mm"] > 0.0
    assert "TV: " in result.output and "iteration(s)" in result.output
    assert recon["rmse_recorded_per_mm"] < recon["rmse_fdk_per_mm"]
    folder = study / "recon"  # both files hold the TV volume; the scan's FDK kept beside them
    tv, mha = (read_volume(folder / name).data for name in ("volume.nii.gz", "volume.mha"))
    np.testing.assert_array_equal(mha, tv)
    assert not np.array_equal(read_volume(folder / "live_volume.mha").data, tv)

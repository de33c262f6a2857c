"""``cbct detector-calibrate`` from the console, and a scan that uses its maps or refuses them."""

from __future__ import annotations

from pathlib import Path

import yaml
from typer.testing import CliRunner

from scanner.corrections import PanelMaps
from scanner.study import Study
from sim.panel import SimPanelSpec
from study.cli import app
from tests.study.test_scan_cli import scan, tiny_protocol

runner = CliRunner()
SERIAL = SimPanelSpec().serial


def calibrate(*args: str, answers: str | None = None):
    return runner.invoke(app, ["detector-calibrate", "--frames", "6", *args], input=answers)


def maps_config(tmp: Path, maps: Path, **fields) -> Path:
    path = tmp / "sim-maps.yaml"
    path.write_text(yaml.safe_dump({"detector_maps": str(maps), **fields}))
    return path


def test_calibrate_then_scan_with_the_maps(tmp_path):
    protocol, maps = tiny_protocol(tmp_path), tmp_path / "maps"
    result = calibrate("--protocol", str(protocol), "--out", str(maps), "--yes")
    assert result.exit_code == 0, result.output
    written = maps / SERIAL / "64x64_Mono16.npz"
    assert written.is_file() and "maps written" in result.output
    made = PanelMaps.load(written)
    assert made.kv == 110 and made.frames == 6 and abs(made.lag - SimPanelSpec().lag) < 0.005
    # the two dead columns are found (the panel's defects are seeded by serial and size)
    assert len(made.summary()["defective_cols"]) == SimPanelSpec().dead_columns

    # never over older maps: refused before anything is exposed
    again = calibrate("--protocol", str(protocol), "--out", str(maps), "--yes")
    assert again.exit_code == 2 and "never overwritten" in again.output
    assert "flood frames at" not in again.output  # refused before the question

    study = tmp_path / "study"
    config = maps_config(tmp_path, maps)
    done = scan(
        "--study", str(study), "--yes", "--protocol", str(protocol), "--backend-config", str(config)
    )
    assert done.exit_code == 0, done.output
    assert f"detector maps of {SERIAL} (64x64 Mono16)" in done.output
    stack = Study.open(study)
    assert stack.verify() == [] and stack.stage("scan")["views"] == 60


def test_a_scan_refuses_maps_of_another_mode_kv_or_age_before_anything_moves(tmp_path):
    protocol, maps = tiny_protocol(tmp_path), tmp_path / "maps"
    assert calibrate("--protocol", str(protocol), "--out", str(maps), "--yes").exit_code == 0

    other_mode = yaml.safe_load(protocol.read_text())
    other_mode["detector"] = {"rows": 96, "cols": 96, "pixel_pitch_mm": 6.4}
    path = tmp_path / "other-mode.yaml"
    path.write_text(yaml.safe_dump(other_mode))
    refused = scan(
        "--study", str(tmp_path / "a"), "--yes", "--protocol", str(path),
        "--backend-config", str(maps_config(tmp_path, maps)),
    )  # fmt: skip
    assert refused.exit_code == 2, refused.output
    assert "mode '96x96 Mono16'" in refused.output and "64x64_Mono16.npz" in refused.output

    other_kv = yaml.safe_load(protocol.read_text())
    other_kv["exposure"]["tube_kv"] = 90
    path = tmp_path / "other-kv.yaml"
    path.write_text(yaml.safe_dump(other_kv))
    refused = scan(
        "--study", str(tmp_path / "b"), "--yes", "--protocol", str(path),
        "--backend-config", str(maps_config(tmp_path, maps)),
    )  # fmt: skip
    assert refused.exit_code == 2, refused.output
    assert "made at 110 kV, the protocol exposes at 90 kV" in refused.output

    refused = scan(
        "--study", str(tmp_path / "c"), "--yes", "--protocol", str(protocol),
        "--backend-config", str(maps_config(tmp_path, maps, max_map_age_days=1e-9)),
    )  # fmt: skip
    assert refused.exit_code == 2, refused.output
    assert "days old, the limit is 1e-09 days" in refused.output
    for name in "abc":
        started = tmp_path / name / "scan" / "views"
        assert not started.exists() or not list(started.iterdir())  # nothing acquired


def test_no_to_the_beam_question_exposes_nothing(tmp_path):
    protocol, maps = tiny_protocol(tmp_path), tmp_path / "maps"
    result = calibrate("--protocol", str(protocol), "--out", str(maps), answers="n\n")
    assert result.exit_code == 2 and "nothing exposed" in result.output
    assert not maps.exists() or not list(maps.rglob("*.npz"))
    few = calibrate("--protocol", str(protocol), "--out", str(maps), "--frames", "2", "--yes")
    assert few.exit_code == 2 and "--frames" in few.output

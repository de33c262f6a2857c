"""``cbct detector-calibrate`` from the console, and a scan that uses its maps or refuses them."""

from __future__ import annotations

from pathlib import Path

import yaml
from typer.testing import CliRunner

from scanner.corrections import PanelMaps
from scanner.study_folder import Study
from sim.panel import SimPanelSpec
from study.cli import app
from tests.study.test_scan_cli import scan, tiny_protocol

runner = CliRunner()
SERIAL = SimPanelSpec().serial


def calibrate(*args: str, answers: str | None = None):
    return runner.invoke(app, ["detector-calibrate", "--frames", "6", *args], input=answers)


def maps_config(tmp: Path, maps: Path, **fields) -> Path:
    path = tmp / f"sim-maps{''.join(f'-{k}' for k in fields)}.yaml"
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

    def edited(name: str, section: str, values: dict) -> Path:
        data = yaml.safe_load(protocol.read_text())
        data[section] = {**data[section], **values}
        path = tmp_path / f"{name}.yaml"
        path.write_text(yaml.safe_dump(data))
        return path

    cases = {  # study: (protocol, backend config, what the refusal says)
        "mode": (
            edited("mode", "detector", {"rows": 96, "cols": 96, "pixel_pitch_mm": 6.4}),
            maps_config(tmp_path, maps),
            ("mode '96x96 Mono16'", "64x64_Mono16.npz"),
        ),
        "kv": (
            edited("kv", "exposure", {"tube_kv": 90}),
            maps_config(tmp_path, maps),
            ("made at 110 kV, the protocol exposes at 90 kV",),
        ),
        "age": (
            protocol,
            maps_config(tmp_path, maps, max_map_age_days=1e-9),
            ("days old, the limit is 1e-09 days",),
        ),
    }
    for name, (path, config, said) in cases.items():
        study = tmp_path / name
        refused = scan(
            "--study", str(study), "--yes", "--protocol", str(path), "--backend-config", str(config)
        )
        assert refused.exit_code == 2, refused.output
        assert all(words in refused.output for words in said), refused.output
        started = study / "scan" / "views"
        assert not started.exists() or not list(started.iterdir())  # nothing acquired


def test_no_to_the_beam_question_exposes_nothing(tmp_path):
    protocol, maps = tiny_protocol(tmp_path), tmp_path / "maps"
    result = calibrate("--protocol", str(protocol), "--out", str(maps), answers="n\n")
    assert result.exit_code == 2 and "nothing exposed" in result.output
    assert not maps.exists() or not list(maps.rglob("*.npz"))
    few = calibrate("--protocol", str(protocol), "--out", str(maps), "--frames", "2", "--yes")
    assert few.exit_code == 2 and "--frames" in few.output

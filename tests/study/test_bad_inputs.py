"""Every command meets the bad inputs of one table: exit status 2, a message naming the option
or the file, and nothing created at its output (or an existing output left as it was)."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from configs import CONFIGS
from recon.geometry import DetectorSpec, circular_orbit
from recon.io import write_projections
from recon.rtk_xml import write_rtk_geometry
from scanner.outputs import TEMP_PREFIX
from study.cli import app

runner = CliRunner()
PROTOCOL = CONFIGS / "protocols" / "demo_knee.yaml"


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """Inputs good and bad, made once: a tiny RTK stack and its geometry, and broken files."""
    root = tmp_path_factory.mktemp("inputs")
    geometry = circular_orbit(8, 600.0, 1000.0, DetectorSpec(rows=16, cols=16, pixel_pitch_mm=2.0))
    write_projections(root / "stack.mha", np.zeros((8, 16, 16), np.float32), 2.0)
    write_rtk_geometry(root / "geometry.xml", geometry)
    whole = (root / "stack.mha").read_bytes()
    (root / "truncated.mha").write_bytes(whole[: len(whole) - 1000])
    (root / "garbage.mha").write_text("not an image\n")
    (root / "garbage.jpg").write_bytes(b"\xff\xd8\xff\xe0" + b"\0" * 200)
    (root / "text.nii.gz").write_text("a text file named like a volume\n")
    (root / "image.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 64)
    (root / "poses.csv").write_text("frame,bone\n")
    (root / "empty").mkdir()
    (root / "a_file").write_text("a file, not a folder\n")
    data = yaml.safe_load(PROTOCOL.read_text(encoding="utf-8"))
    data["exposure"]["tube_kv"] = float("nan")
    (root / "nan_kv.yaml").write_text(yaml.safe_dump(data))
    return root


def _out(case: str, files, work):
    """The output a row names: new, an existing folder with data, a file, or under a file."""
    if case == "taken":
        (work / "taken").mkdir()
        (work / "taken" / "kept.txt").write_text("kept")
        return work / "taken"
    if case == "taken.nii.gz":
        (work / "taken.nii.gz").write_bytes(b"kept")
        return work / "taken.nii.gz"
    if case == "under_a_file":
        shutil.copy(files / "a_file", work / "a_file")
        return work / "a_file" / "out"
    return work / case


# command, its arguments ({F}: the inputs folder, {OUT}: the row's output), the output case,
# and what the message must name
# fmt: off
ROWS = [
    ("plan", "--protocol {F}/missing.yaml --out {OUT}", "study", "missing.yaml"),
    ("plan", "--protocol {F}/nan_kv.yaml --out {OUT}", "study", "tube_kv"),
    ("plan", f"--protocol {PROTOCOL} --out {{OUT}}", "taken", "--out"),
    ("simulate-scan", f"--protocol {PROTOCOL} --out {{OUT}} --vibration-mm -1", "scan",
     "--vibration-mm"),
    ("simulate-scan", f"--protocol {PROTOCOL} --out {{OUT}}", "under_a_file", "is a file"),
    ("calibrate", f"--projections {{F}}/missing.mha --geometry {{F}}/geometry.xml "
     f"--protocol {PROTOCOL} --study {{OUT}}", "study", "missing.mha"),
    ("calibrate-fluoro", "--grid {F}/garbage.mha --geometry {F}/geometry.xml --out {OUT}",
     "warp.json", "garbage.mha"),
    ("calibrate-fluoro", "--grid {F}/stack.mha --geometry {F}/geometry.xml --out {OUT}",
     "warp.txt", ".json"),
    ("recon", "--projections {F}/truncated.mha --geometry {F}/geometry.xml --out {OUT}",
     "v.nii.gz", "truncated.mha"),
    ("recon", "--projections {F}/stack.mha --geometry {F}/geometry.xml --out {OUT} "
     "--min-coverage-deg 9999", "v.nii.gz", "--min-coverage-deg"),
    ("recon", "--projections {F}/stack.mha --geometry {F}/geometry.xml --out {OUT}",
     "taken.nii.gz", "--out"),
    ("recon", "--projections {F}/stack.mha --geometry {F}/geometry.xml --out {OUT}",
     "v.xyz", "--out"),
    ("recon", "--projections {F}/stack.mha --geometry {F}/geometry.xml --out {OUT} "
     "--preview {F}/p.xyz", "v.nii.gz", "--preview"),
    ("segment", "--volume {F}/text.nii.gz --out {OUT}", "labels.nii.gz", "text.nii.gz"),
    ("segment", "--volume {F}/stack.mha --out {OUT} --unit kelvin", "labels.nii.gz", "--unit"),
    ("assess", "--poses {F}/poses.csv --labels {F}/stack.mha --out {OUT} "
     "--volume {F}/text.nii.gz", "report", "text.nii.gz"),
    ("assess", "--poses {F}/poses.csv --labels {F}/stack.mha --out {OUT} --volume {F}/empty",
     "report", "0 DICOM series"),
    ("assess", "--poses {F}/poses.csv --labels {F}/stack.mha --out {OUT} --side middle",
     "report", "--side"),
    ("export", "--poses {F}/poses.csv --labels {F}/stack.mha --out {OUT} "
     "--volume {F}/image.png", "export", "image.png"),
    ("export", "--poses {F}/poses.csv --labels {F}/stack.mha --out {OUT}", "taken", "--out"),
    ("register", "--frames {F}/missing.mha --geometry {F}/geometry.xml --volume {F}/stack.mha "
     "--labels {F}/stack.mha --out {OUT}", "poses", "missing.mha"),
    ("register", "--frames {F}/stack.mha --geometry {F}/geometry.xml --volume {F}/stack.mha "
     "--labels {F}/stack.mha --out {OUT} --frames-range 5:2", "poses", "--frames-range"),
    ("register", "--frames {F}/stack.mha --geometry {F}/geometry.xml --volume {F}/stack.mha "
     "--labels {F}/stack.mha --out {OUT} --frames-range first:last", "poses", "--frames-range"),
    ("scan", "--protocol {F}/nan_kv.yaml --study {OUT} --yes", "study", "tube_kv"),
    ("scan", f"--protocol {PROTOCOL} --study {{OUT}} --yes --recon-voxel-mm 99", "study",
     "--recon-voxel-mm"),
    ("scan", "--study {F}/empty --resume --yes", "study", "not a study folder"),
    ("move", "--study {F}/empty --to nowhere --yes", "study", "--to"),
    ("demo", "--out {OUT} --quick", "under_a_file", "a_file"),
    ("batch", "transmogrify {F}/empty --out {OUT}", "cohort", "unknown action"),
    ("recon", "--projections {F}/stack.mha --geometry {F}/geometry.xml --out {OUT} "
     "--spacing-mm 0", "v.nii.gz", "--spacing-mm"),
    ("recon", "--projections {F}/stack.mha --geometry {F}/geometry.xml --out {OUT} "
     "--size 0 10 10", "v.nii.gz", "--size"),
    ("simulate-scan", f"--protocol {PROTOCOL} --out {{OUT}} --voxel-mm 0", "scan", "--voxel-mm"),
    ("scan", f"--protocol {PROTOCOL} --study {{OUT}} --yes --phantom-voxel-mm 9", "study",
     "--phantom-voxel-mm"),
    ("segment", "--volume {F}/stack.mha --out {OUT} --effective-energy-kev 5", "labels.nii.gz",
     "--effective-energy-kev"),
    ("export", "--poses {F}/poses.csv --labels {F}/stack.mha --out {OUT} --volume {F}/empty",
     "export", "0 DICOM series"),
    ("register", "--frames {F}/stack.mha --calibration {F}/missing.txt --implant "
     "femur={F}/stack.mha --out {OUT}", "poses", "missing.txt: no such file or folder"),
    ("simulate-scan", f"--protocol {CONFIGS}/phantoms/knee.yaml --out {{OUT}}", "scan",
     "not a scan protocol file?"),
    ("assess", "--poses {F}/poses.csv --labels {F}/stack.mha --out {OUT} --overlays "
     "{F}/missing", "report", "--overlays"),
    ("register", "--frames {F}/garbage.jpg --geometry {F}/geometry.xml --volume {F}/stack.mha "
     "--labels {F}/stack.mha --out {OUT}", "poses", "garbage.jpg: not frames this reads"),
    ("recon", "--projections {F}/stack.mha --geometry {F}/geometry.xml --out {OUT} "
     "--method tv --iterations 0", "v.nii.gz", "--iterations 0: give 1 or more"),
    ("recon", "--projections {F}/stack.mha --geometry {F}/geometry.xml --out {OUT} "
     "--method tv --tv-weight -0.01", "v.nii.gz", "--tv-weight -0.01: give 0 or more 1/mm"),
    ("recon", "--projections {F}/stack.mha --geometry {F}/geometry.xml --out {OUT} "
     "--method art", "v.nii.gz", "--method art: choose one of fdk, sart, tv"),
    ("recon", "--projections {F}/stack.mha --geometry {F}/geometry.xml --out {OUT} "
     "--views-every 2", "v.nii.gz", "--views-every 2 keeps 4 of 8 views: at least 20"),
    ("demo", "--out {OUT} --quick --protocol {F}/missing.yaml", "demo", "missing.yaml"),
    ("demo", "--out {OUT} --size tiny", "demo", "--size tiny: choose one of full, quick, smoke"),
    ("demo", "--out {OUT} --quick --size smoke", "demo", "contradicts --size smoke"),
]
# fmt: on


@pytest.mark.parametrize(
    ("command", "args", "out_case", "named"), ROWS, ids=[f"{r[0]}-{i}" for i, r in enumerate(ROWS)]
)
def test_a_bad_input_is_refused_with_its_name_and_nothing_written(
    files, tmp_path, command, args, out_case, named
):
    out = _out(out_case, files, tmp_path)
    before = sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*"))
    argv = [command, *args.format(F=files, OUT=out).split()]
    result = runner.invoke(app, argv, terminal_width=400)
    assert result.exit_code == 2, (argv, result.output, result.exception)
    assert named in result.output, (argv, result.output)
    assert "Traceback" not in result.output
    after = sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*"))
    assert after == before, argv  # nothing at the output, no temporary left
    assert not [p for p in files.rglob("*") if p.name.startswith(TEMP_PREFIX)]


@pytest.mark.parametrize(
    "args",
    [
        "recon --projections {F}/stack.mha --geometry {F}/geometry.xml --out {OUT}/v.nii.gz",
        "segment --volume {F}/stack.mha --out {OUT}/labels.nii.gz --unit 1/mm",
        "assess --poses {F}/poses.csv --labels {F}/stack.mha --out {OUT}/report",
    ],
)
def test_an_output_on_a_read_only_filesystem_is_refused_before_the_work(files, tmpfs, args):
    """Unwritable for root too: a read-only tmpfs (skipped where mounting is not allowed)."""
    disk = tmpfs("ro,size=64k")
    result = runner.invoke(app, args.format(F=files, OUT=disk).split(), terminal_width=400)
    assert result.exit_code == 2, result.output
    assert f"--out {disk}/" in result.output and "cannot write in" in result.output
    assert "(a read-only file system)" in result.output

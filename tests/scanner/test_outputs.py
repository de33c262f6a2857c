"""scanner.outputs: a command's outputs appear only when its work succeeded."""

from __future__ import annotations

import os

import pytest

from scanner.outputs import TEMP_PREFIX, Output, new_outputs


def _leftovers(folder):
    return sorted(p.name for p in folder.rglob("*") if p.name.startswith(TEMP_PREFIX))


def test_outputs_and_their_companions_appear_when_the_work_succeeds(tmp_path):
    volume, report = tmp_path / "deep" / "er" / "volume.mhd", tmp_path / "report"
    outputs = (Output(volume, "--out", suffixes=(".mhd",)), Output(report, "--report"))
    with new_outputs(*outputs) as (volume_at, report_at):
        assert volume_at.name == "volume.mhd" and report_at.name == "report"
        assert not (tmp_path / "deep").exists()  # missing folders wait for the result
        volume_at.write_text("ElementDataFile = volume.raw\n")
        (volume_at.parent / "volume.raw").write_bytes(b"\0" * 8)
        report_at.mkdir()
        (report_at / "index.html").write_text("<html/>")
        assert not volume.exists() and not report.exists()
    assert volume.read_text().startswith("ElementDataFile")
    assert (volume.parent / "volume.raw").stat().st_size == 8
    assert (report / "index.html").is_file()
    assert _leftovers(tmp_path) == []


@pytest.mark.parametrize("error", [ValueError("bad frame"), KeyboardInterrupt()])
def test_a_failure_leaves_nothing(tmp_path, error):
    out = tmp_path / "out"
    with pytest.raises(type(error)), new_outputs(Output(out, "--out")) as (at,):
        at.mkdir()
        (at / "poses.csv").write_text("frame,bone\n")
        raise error
    assert sorted(os.listdir(tmp_path)) == []


def test_an_output_not_written_is_skipped(tmp_path):
    with new_outputs(Output(tmp_path / "a.png", "--preview")):
        pass
    assert sorted(os.listdir(tmp_path)) == []


def test_an_empty_folder_may_take_the_output_where_allowed(tmp_path):
    (tmp_path / "out").mkdir()
    with new_outputs(Output(tmp_path / "out", "--out", empty_ok=True)) as (at,):
        at.mkdir()
        (at / "x").write_text("1")
    assert (tmp_path / "out" / "x").read_text() == "1"
    with pytest.raises(FileExistsError, match=r"--out .*out: the folder exists and is not empty"):
        with new_outputs(Output(tmp_path / "out", "--out", empty_ok=True)):
            pytest.fail("the block ran")


@pytest.mark.parametrize(
    ("make", "output", "error", "words"),
    [
        ("file", Output, FileExistsError, "the file exists; choose a new name"),
        (
            None,
            lambda p, o: Output(p.with_suffix(".xyz"), o, suffixes=(".png",)),
            ValueError,
            "must end with .png",
        ),
        ("parent-file", Output, ValueError, "is a file, not a folder"),
    ],
)
def test_bad_outputs_are_refused_before_the_work(tmp_path, make, output, error, words):
    path = tmp_path / "slices.png"
    if make == "file":
        path.write_bytes(b"kept")
    elif make == "parent-file":
        (tmp_path / "notes").write_text("a file")
        path = tmp_path / "notes" / "slices.png"
    with pytest.raises(error, match=words) as raised:
        with new_outputs(output(path, "--preview")):
            pytest.fail("the block ran")
    assert "--preview" in str(raised.value)
    assert _leftovers(tmp_path) == []
    if make == "file":
        assert path.read_bytes() == b"kept"


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes in any folder")
def test_an_unwritable_folder_is_refused_before_the_work(tmp_path):
    folder = tmp_path / "ro"
    folder.mkdir(mode=0o555)
    with pytest.raises(PermissionError, match="cannot write in"):
        with new_outputs(Output(folder / "v.mha", "--out")):
            pytest.fail("the block ran")


def test_an_output_that_appears_meanwhile_is_not_overwritten(tmp_path):
    out = tmp_path / "v.mha"
    with pytest.raises(FileExistsError, match="appeared while the command ran"):
        with new_outputs(Output(out, "--out")) as (at,):
            at.write_text("new")
            out.write_text("someone else's")
    assert out.read_text() == "someone else's"
    (kept,) = _leftovers(tmp_path)
    assert (tmp_path / kept / "v.mha").read_text() == "new"

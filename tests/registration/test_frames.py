"""Tests of registration.frames: fluoroscopy frames from .mha stacks and clinical DICOM."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk

from recon.io import write_projections
from registration.frames import exposed_field, read_frames

data_store = pytest.importorskip("data_store", reason="pydicom-data (dev extra) ships RG3_UNCR")


def _real_radiograph() -> Path:
    path = Path(data_store.__file__).parent / "data" / "RG3_UNCR.dcm"
    assert path.exists(), path
    return path


def test_a_real_monochrome1_radiograph_is_inverted_linearly() -> None:
    path = _real_radiograph()
    with pytest.raises(ValueError, match="no pixel spacing"):
        read_frames(path)
    frames = read_frames(path, pixel_pitch_mm=0.2)
    raw = sitk.GetArrayFromImage(sitk.ReadImage(str(path))).astype(np.float64).reshape(-1)
    assert frames.photometric == "MONOCHROME1"
    assert frames.data.shape[0] == 1 and frames.data[0].size == raw.size
    assert frames.pixel_pitch_mm == (0.2, 0.2)
    assert frames.times_s is None
    # MONOCHROME1 shows its minimum white: brightness (our attenuation stand-in) = max - value
    assert np.corrcoef(frames.data.reshape(-1), raw)[0, 1] == pytest.approx(-1.0, abs=1e-9)
    low, high = np.percentile(frames.data, (0.5, 99.5))
    assert low == pytest.approx(0.0, abs=1e-6) and high == pytest.approx(1.0, abs=1e-6)


def test_a_dicom_folder_keeps_order_spacing_and_timing(tmp_path) -> None:
    rng = np.random.default_rng(0)
    stack = rng.integers(100, 4000, size=(3, 24, 32)).astype(np.uint16)
    for k, image in enumerate(stack):
        item = sitk.GetImageFromArray(image)
        item.SetSpacing((0.25, 0.3))  # (column, row) mm -> Pixel Spacing "0.3\\0.25"
        writer = sitk.ImageFileWriter()
        writer.KeepOriginalImageUIDOn()
        for key, value in {
            "0008|0060": "RF",
            "0028|0004": "MONOCHROME2",
            "0018|1063": "66.7",
            "0020|0013": str(k + 1),
            "0020|000e": "1.2.826.0.1.3680043.2.1125.1.1",
            "0020|000d": "1.2.826.0.1.3680043.2.1125.1.2",
            "0020|0032": f"0\\0\\{k}",
        }.items():
            item.SetMetaData(key, value)
        writer.SetFileName(str(tmp_path / f"frame{k}.dcm"))
        writer.Execute(item)
    frames = read_frames(tmp_path)
    assert frames.photometric == "MONOCHROME2"
    assert frames.pixel_pitch_mm == (0.25, 0.3)  # (column, row) spacing
    assert frames.times_s == pytest.approx([0.0, 0.0667, 0.1334])
    assert np.corrcoef(frames.data.ravel(), stack.astype(float).ravel())[0, 1] == pytest.approx(
        1.0, abs=1e-9
    )


def test_an_mha_stack_is_taken_as_line_integrals(tmp_path) -> None:
    data = np.random.default_rng(1).random((4, 16, 20)).astype(np.float32)
    write_projections(tmp_path / "frames.mha", data, 0.6)
    frames = read_frames(tmp_path / "frames.mha")
    assert frames.photometric == "line integrals"
    assert np.array_equal(frames.data, data)
    assert frames.pixel_pitch_mm == pytest.approx((0.6, 0.6))


def test_missing_frames_are_named(tmp_path) -> None:
    with pytest.raises(FileNotFoundError, match=r"nope\.mha"):
        read_frames(tmp_path / "nope.mha")


def _xa_multiframe(path: Path, stored: np.ndarray, relation: str, sign: str) -> Path:
    """One multi-frame XA file (GDCM writes a 3-D image as one), 0.3 mm imager pixels."""
    image = sitk.GetImageFromArray(stored)
    image.SetSpacing((0.3, 0.3, 1.0))
    for key, value in {
        "0008|0060": "XA",
        "0028|0004": "MONOCHROME2",
        "0028|1040": relation,
        "0028|1041": sign,
        "0018|1063": "66.7",
    }.items():
        image.SetMetaData(key, value)
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    writer.SetFileName(str(path))
    writer.Execute(image)
    return path


@pytest.mark.parametrize(
    ("relation", "sign", "encode"),
    [
        ("LIN", "1", lambda p: 3000.0 * np.exp(-p)),  # intensity: bone dark
        ("LOG", "1", lambda p: 1000.0 * (5.0 - p)),  # log intensity: bone dark
        ("LOG", "-1", lambda p: 1000.0 * p + 100.0),  # attenuation: bone bright
    ],
)
def test_fluoroscopy_values_follow_their_pixel_intensity_relationship(
    tmp_path, relation, sign, encode
) -> None:
    """Whatever the encoding, the frames come out as an affine image of the line integral
    (correlation 1 up to the 16-bit rounding), never inverted."""
    rng = np.random.default_rng(4)
    line_integrals = np.cumsum(rng.random((3, 24, 32)), axis=2) / 8.0  # 0..4, smooth ramps
    stored = np.round(encode(line_integrals)).astype(np.uint16)
    frames = read_frames(_xa_multiframe(tmp_path / "xa.dcm", stored, relation, sign))
    assert frames.data.shape == (3, 24, 32) and frames.pixel_pitch_mm == (0.3, 0.3)
    assert frames.times_s == pytest.approx([0.0, 0.0667, 0.1334])
    assert relation in frames.stand_in and sign.lstrip("+") in frames.stand_in
    r = np.corrcoef(frames.data.ravel(), line_integrals.ravel())[0, 1]
    assert r > 0.9999


def test_a_sign_dicom_does_not_allow_is_refused_with_its_tag(tmp_path) -> None:
    stored = np.full((2, 8, 8), 100, np.uint16)
    with pytest.raises(ValueError, match=r"\(0028,1041\) is '2'"):
        read_frames(_xa_multiframe(tmp_path / "xa.dcm", stored, "LIN", "2"))


def test_the_exposed_field_leaves_out_the_dark_round_border_but_not_a_dark_implant() -> None:
    """An image intensifier's round field (nothing outside it in any frame) and, inside it, a
    metal part as dark as no signal in every frame: only the border's dark region is outside."""
    rng = np.random.default_rng(1)
    n = 64
    intensity = rng.uniform(200.0, 4000.0, size=(3, n, n))
    v, u = np.mgrid[:n, :n] - (n - 1) / 2.0
    round_field = np.hypot(u, v) <= 0.45 * n
    intensity[:, ~round_field] = 0.0
    intensity[:, 28:36, 28:36] = 0.0  # the implant: no signal through it either
    attenuation = -np.log(np.maximum(intensity, 1.0))
    field = exposed_field(attenuation)
    np.testing.assert_array_equal(field, round_field)
    assert exposed_field(attenuation[:, 14:-14, 14:-14]) is None  # a crop inside the field


def test_images_by_glob_or_folder_with_their_polarity_and_shutters(tmp_path) -> None:
    """8-bit PNGs, attenuation dark, black shutter bars at the sides (as JTML's frames): read
    in sorted order at the given pitch, inverted, the bars outside the field; without a pitch,
    refused; the other polarity keeps the values."""
    rng = np.random.default_rng(2)
    stack = rng.integers(40, 220, size=(3, 32, 48)).astype(np.uint8)
    stack[:, :, :6] = 0
    stack[:, :, -5:] = 0
    stack[1, 10:14, 20:26] = 0  # an implant as dark as the bars, inside the field
    for k in (2, 0, 1):  # written out of order
        sitk.WriteImage(sitk.GetImageFromArray(stack[k]), str(tmp_path / f"frame_{k:02d}.png"))
    (tmp_path / "notes.txt").write_text("not a frame")
    for source in (tmp_path, tmp_path / "frame_*.png"):
        frames = read_frames(source, pixel_pitch_mm=0.373)
        assert frames.stand_in == "max - value (images, attenuation dark)"
        assert frames.pixel_pitch_mm == (0.373, 0.373)
        raw = 255.0 - stack.astype(np.float64)
        corr = np.corrcoef(frames.data[:, :, 6:-5].ravel(), raw[:, :, 6:-5].ravel())[0, 1]
        assert corr == pytest.approx(1.0, abs=1e-9)
        assert frames.field[:, 6:-5].all() and not frames.field[:, :6].any()
        assert not frames.field[:, -5:].any()
    bright = read_frames(tmp_path, pixel_pitch_mm=0.373, polarity="bright")
    assert np.corrcoef(bright.data.ravel(), frames.data.ravel())[0, 1] == pytest.approx(-1.0)
    with pytest.raises(ValueError, match="images carry no pixel size"):
        read_frames(tmp_path)
    with pytest.raises(FileNotFoundError, match="matches no file"):
        read_frames(tmp_path / "nothing_*.tif", pixel_pitch_mm=0.3)


def test_images_as_a_list_keep_its_order(tmp_path) -> None:
    values = (30, 90, 60)
    names = []
    for k, value in enumerate(values):
        name = tmp_path / f"{'cab'[k]}.tif"
        sitk.WriteImage(sitk.GetImageFromArray(np.full((8, 8), value, np.uint16)), str(name))
        names.append(name)
    frames = read_frames(names, pixel_pitch_mm=0.2, polarity="bright")
    assert frames.data[:, 0, 0].argsort().tolist() == [0, 2, 1]  # 30, 60, 90: the list's order
    with pytest.raises(FileNotFoundError, match="a list of frames names TIFF or PNG files"):
        read_frames([names[0], tmp_path / "x.mha"], pixel_pitch_mm=0.2)

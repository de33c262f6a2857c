"""Static scans from other scanners: NIfTI/MetaImage without our unit note and DICOM CT series,
in HU or 1/mm (recon.static_volume, recon.attenuation, recon.dicom.read_dicom_series)."""

from __future__ import annotations

import uuid
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk

from recon.attenuation import hu_to_mu, mu_water_per_mm
from recon.dicom import read_dicom_series, write_dicom_series
from recon.static_volume import read_attenuation
from recon.volume import Volume, VolumeGrid

GRID = VolumeGrid((6, 5, 4), (0.6, 0.7, 1.5), (-20.0, 35.0, 400.0))
NIST_WATER_70KEV_PER_MM = 0.01937  # NIST water, 60 and 80 keV interpolated log-log


def _knee_hu() -> np.ndarray:
    """CT numbers of a leg-like block: air, fat, muscle, cortical bone (HU), [z, y, x]."""
    rng = np.random.default_rng(3)
    tissue = np.array([-1000.0, -100.0, 50.0, 1400.0])
    return tissue[rng.integers(0, 4, GRID.shape)] + rng.normal(0, 8, GRID.shape)


def _plain_file(path: Path, data: np.ndarray, grid: VolumeGrid = GRID) -> Path:
    """A volume written by SimpleITK alone, as another tool would: no unit note."""
    image = sitk.GetImageFromArray(data.astype(np.float32))
    image.SetSpacing(grid.spacing_mm)
    image.SetOrigin(grid.origin_mm)
    sitk.WriteImage(image, str(path))
    return path


def test_water_attenuation_follows_nist():
    assert mu_water_per_mm(60.0) == pytest.approx(0.02059, rel=1e-12)
    assert mu_water_per_mm(100.0) == pytest.approx(0.01707, rel=1e-12)
    assert mu_water_per_mm(70.0) == pytest.approx(NIST_WATER_70KEV_PER_MM, rel=2e-4)
    with pytest.raises(ValueError, match="effective energy 300"):
        mu_water_per_mm(300.0)


@pytest.mark.parametrize("suffix", [".nii.gz", ".mha"])
def test_a_ct_in_hu_without_a_unit_is_told_by_its_values_and_converted(tmp_path, suffix):
    hu = _knee_hu()
    path = _plain_file(tmp_path / f"ct{suffix}", hu)
    volume, source = read_attenuation(path)
    assert volume.unit == "1/mm" and volume.grid.shape == GRID.shape
    np.testing.assert_allclose(volume.grid.spacing_mm, GRID.spacing_mm, rtol=1e-6)  # float32
    expected = np.maximum(NIST_WATER_70KEV_PER_MM * (1 + hu / 1000), 0)
    np.testing.assert_allclose(volume.data, expected, rtol=3e-4, atol=1e-7)
    assert source.unit == "HU" and source.unit_from == "values"
    assert source.effective_energy_kev == 70.0
    assert source.mu_water_per_mm == pytest.approx(NIST_WATER_70KEV_PER_MM, rel=2e-4)
    at_100 = read_attenuation(path, "HU", effective_energy_kev=100.0)[0]
    expected = np.maximum(0.01707 * (1 + hu / 1000), 0)
    np.testing.assert_allclose(at_100.data, expected, rtol=1e-5, atol=1e-8)  # float32 HU


def test_attenuation_without_a_unit_is_taken_as_it_is(tmp_path):
    mu = np.clip(NIST_WATER_70KEV_PER_MM * (1 + _knee_hu() / 1000), 0, None)
    volume, source = read_attenuation(_plain_file(tmp_path / "mu.nii.gz", mu))
    np.testing.assert_allclose(volume.data, mu, rtol=1e-6)
    assert (source.unit, source.unit_from, source.effective_energy_kev) == ("1/mm", "values", None)


def test_a_unit_the_values_contradict_and_values_that_say_nothing_are_refused(tmp_path):
    hu_file = _plain_file(tmp_path / "hu.nii.gz", _knee_hu())
    with pytest.raises(ValueError, match=r"CT numbers \(HU\), not attenuation in 1/mm.*--unit hu"):
        read_attenuation(hu_file, "1/mm")
    mu = np.full(GRID.shape, NIST_WATER_70KEV_PER_MM)
    with pytest.raises(ValueError, match="attenuation in 1/mm, not CT numbers"):
        read_attenuation(_plain_file(tmp_path / "mu.mha", mu), "HU")
    water = np.random.default_rng(1).normal(0.0, 3.0, GRID.shape)  # a water phantom in HU
    flat = _plain_file(tmp_path / "water.nii.gz", water)
    with pytest.raises(ValueError, match=r"could be CT numbers or attenuation.*--unit hu or"):
        read_attenuation(flat)
    volume, source = read_attenuation(flat, "HU")
    assert source.unit_from == "option"
    assert float(volume.data.mean()) == pytest.approx(NIST_WATER_70KEV_PER_MM, rel=1e-3)


def test_our_files_state_their_unit(tmp_path):
    from recon.io import write_volume

    path = write_volume(tmp_path / "v.nii.gz", Volume(_knee_hu(), GRID, "HU"))
    volume, source = read_attenuation(path)
    assert source.unit_from == "file" and source.unit == "HU"
    with pytest.raises(ValueError, match="states unit 'HU', but '1/mm' was given"):
        read_attenuation(path, "1/mm")
    labels = write_volume(tmp_path / "l.nii.gz", Volume(np.ones(GRID.shape), GRID, "label"))
    with pytest.raises(ValueError, match="a label volume, not a scan"):
        read_attenuation(labels)
    expected = hu_to_mu(Volume(_knee_hu(), GRID, "HU"), 70.0).data  # float32 HU in the file
    np.testing.assert_allclose(volume.data, expected, rtol=1e-6, atol=1e-8)


def _scanner_series(folder: Path, hu: np.ndarray, skip: int | None = None, modality="CT"):
    """A CT series as a scanner writes it, slice by slice with SimpleITK's GDCM writer (not
    ours): rows running anterior to posterior reversed (Image Orientation (1,0,0, 0,-1,0)),
    slices listed top down, stored with a rescale intercept of -1024 (GDCM stores HU + 1024);
    ``skip`` leaves one slice out."""
    folder.mkdir()
    series, frame = f"2.25.{uuid.uuid4().int}", f"2.25.{uuid.uuid4().int}"
    sx, sy, sz = GRID.spacing_mm
    direction = np.diag([1.0, -1.0, -1.0])  # y reversed; slices listed top down
    top = np.asarray(GRID.origin_mm) + np.array([0.0, GRID.shape[1] - 1, GRID.shape[0] - 1]) * [
        0.0,
        sy,
        sz,
    ]
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    for k in range(GRID.shape[0]):
        if k == skip:
            continue
        image = sitk.GetImageFromArray(hu[::-1, ::-1][k : k + 1].astype(np.float32))
        image.SetSpacing((sx, sy, sz))
        position = top - [0.0, 0.0, k * sz]
        image.SetOrigin(tuple(position))
        image.SetDirection(direction.ravel().tolist())
        tags = {
            "0008|0060": modality,
            "0008|0016": "1.2.840.10008.5.1.4.1.1.2",
            "0008|0018": f"2.25.{uuid.uuid4().int}",
            "0020|000e": series,
            "0020|0052": frame,
            "0020|0013": str(k + 1),
            "0020|0032": "\\".join(f"{x:.6f}" for x in position),
            "0020|0037": "1\\0\\0\\0\\-1\\0",
            "0028|0100": "16",
            "0028|0101": "16",
            "0028|0102": "15",
            "0028|0103": "0",
            "0028|1052": "-1024",
            "0028|1053": "1",
        }
        for key, value in tags.items():
            image.SetMetaData(key, value)
        writer.SetFileName(str(folder / f"IM{k:04d}.dcm"))
        writer.Execute(image)
    return folder


def test_a_scanner_ct_series_reads_in_hu_on_our_grid(tmp_path):
    hu = np.round(_knee_hu())
    volume = read_dicom_series(_scanner_series(tmp_path / "ct", hu))
    assert volume.unit == "HU"
    np.testing.assert_allclose(volume.grid.origin_mm, GRID.origin_mm, atol=1e-4)
    np.testing.assert_allclose(volume.grid.spacing_mm, GRID.spacing_mm, atol=1e-6)
    np.testing.assert_allclose(volume.data, hu, atol=1e-4)
    attenuation, source = read_attenuation(tmp_path / "ct")
    assert source.unit == "HU" and source.unit_from == "file"
    np.testing.assert_allclose(attenuation.data, hu_to_mu(volume, 70.0).data, rtol=1e-6)


def test_our_own_series_reads_back(tmp_path):
    mu = np.clip(NIST_WATER_70KEV_PER_MM * (1 + _knee_hu() / 1000), 0, None)
    water = mu_water_per_mm(70.0)
    write_dicom_series(tmp_path / "dcm", Volume(mu, GRID, "1/mm"), water)
    volume, _ = read_attenuation(tmp_path / "dcm")
    assert volume.grid.shape == GRID.shape
    np.testing.assert_allclose(volume.data, mu, atol=0.5e-3 * water + 1e-7)  # 0.5 HU steps


def test_broken_series_are_refused_with_the_tag_named(tmp_path):
    hu = _knee_hu()
    with pytest.raises(ValueError, match=r"unequal slice gaps \(a missing slice\?\)"):
        read_dicom_series(_scanner_series(tmp_path / "gap", hu, skip=2))
    with pytest.raises(ValueError, match=r"Modality \(0008,0060\) is 'MR'"):
        read_dicom_series(_scanner_series(tmp_path / "mr", hu, modality="MR"))
    (tmp_path / "empty").mkdir()
    with pytest.raises(OSError, match="no DICOM series"):
        read_dicom_series(tmp_path / "empty")


def test_a_tilted_ct_series_reads_in_hu_where_its_voxels_are(tmp_path):
    """A series whose slices are tilted 15 deg about x (Image Orientation (1,0,0, 0,c,s)),
    written slice by slice by GDCM, holding CT numbers that vary linearly in space: read onto
    an axis-aligned grid, each voxel inside the tilted block holds the CT number of its own
    world position (trilinear interpolation reproduces a linear field; int16 storage rounds by
    0.5 HU)."""
    folder = tmp_path / "tilted"
    folder.mkdir()
    c, s = np.cos(np.radians(15)), np.sin(np.radians(15))
    direction = np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])  # columns: row, column, normal
    spacing, shape = np.array([0.7, 0.8, 1.2]), (8, 10, 12)  # (x, y, z) spacing; [k, j, i]
    origin = np.array([-4.0, 6.0, 300.0])
    gradient, series = np.array([2.0, -3.0, 5.0]), f"2.25.{uuid.uuid4().int}"
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    for k in range(shape[0]):
        j, i = np.indices(shape[1:])
        position = origin + direction[:, 2] * spacing[2] * k
        world = (
            position + (direction[:, :2] @ (spacing[:2, None] * np.stack([i.ravel(), j.ravel()]))).T
        )
        image = sitk.GetImageFromArray(
            np.round(world @ gradient).reshape(1, *shape[1:]).astype(np.int16)
        )
        image.SetSpacing(spacing.tolist())
        image.SetOrigin(position.tolist())
        image.SetDirection(direction.ravel().tolist())
        tags = {
            "0008|0060": "CT",
            "0008|0016": "1.2.840.10008.5.1.4.1.1.2",
            "0020|000e": series,
            "0020|0013": str(k + 1),
            "0020|0032": "\\".join(f"{x:.6f}" for x in position),
            "0020|0037": "\\".join(f"{x:.6f}" for x in direction[:, :2].T.ravel()),
        }
        for key, value in tags.items():
            image.SetMetaData(key, value)
        writer.SetFileName(str(folder / f"IM{k:04d}.dcm"))
        writer.Execute(image)
    volume = read_dicom_series(folder)
    assert volume.unit == "HU" and volume.grid.spacing_mm == (0.7, 0.7, 0.7)
    zz, yy, xx = np.indices(volume.grid.shape).reshape(3, -1)
    centres = np.asarray(volume.grid.origin_mm) + 0.7 * np.stack([xx, yy, zz], axis=1)
    index = np.linalg.solve(direction, (centres - origin).T).T / spacing
    inside = np.all((index >= 0) & (index <= np.array(shape[::-1]) - 1), axis=1)
    assert inside.sum() > 0.2 * inside.size
    np.testing.assert_allclose(
        volume.data.ravel()[inside], centres[inside] @ gradient, atol=0.5 + 1e-3
    )

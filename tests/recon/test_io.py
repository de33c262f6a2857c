"""Tests of recon.io (volumes, projection stacks), recon.dicom and recon.preview."""

from __future__ import annotations

import gzip
import io as std_io
from pathlib import Path

import matplotlib.image as mpimg
import numpy as np
import pytest
import SimpleITK as sitk
from scipy.spatial.transform import Rotation

from recon.dicom import CT_IMAGE_STORAGE, rescale_for, write_dicom_series
from recon.io import (
    ImageFileError,
    ProjectionStack,
    encode_projections,
    read_projections,
    read_volume,
    write_projections,
    write_volume,
)
from recon.preview import (
    DPI,
    FIGSIZE_IN,
    orthogonal_slices,
    render_orthogonal_slices,
    save_orthogonal_slices,
)
from recon.volume import Volume, VolumeGrid

SPACING = (0.5, 0.75, 1.25)
ORIGIN = (-10.25, 20.5, 30.75)

NIFTI1_HEADER = np.dtype(
    [
        ("sizeof_hdr", "<i4"),
        ("data_type", "S10"),
        ("db_name", "S18"),
        ("extents", "<i4"),
        ("session_error", "<i2"),
        ("regular", "S1"),
        ("dim_info", "u1"),
        ("dim", "<i2", (8,)),
        ("intent_p1", "<f4"),
        ("intent_p2", "<f4"),
        ("intent_p3", "<f4"),
        ("intent_code", "<i2"),
        ("datatype", "<i2"),
        ("bitpix", "<i2"),
        ("slice_start", "<i2"),
        ("pixdim", "<f4", (8,)),
        ("vox_offset", "<f4"),
        ("scl_slope", "<f4"),
        ("scl_inter", "<f4"),
        ("slice_end", "<i2"),
        ("slice_code", "u1"),
        ("xyzt_units", "u1"),
        ("cal_max", "<f4"),
        ("cal_min", "<f4"),
        ("slice_duration", "<f4"),
        ("toffset", "<f4"),
        ("glmax", "<i4"),
        ("glmin", "<i4"),
        ("descrip", "S80"),
        ("aux_file", "S24"),
        ("qform_code", "<i2"),
        ("sform_code", "<i2"),
        ("quatern_b", "<f4"),
        ("quatern_c", "<f4"),
        ("quatern_d", "<f4"),
        ("qoffset_x", "<f4"),
        ("qoffset_y", "<f4"),
        ("qoffset_z", "<f4"),
        ("srow_x", "<f4", (4,)),
        ("srow_y", "<f4", (4,)),
        ("srow_z", "<f4", (4,)),
        ("intent_name", "S16"),
        ("magic", "S4"),
    ]
)
assert NIFTI1_HEADER.itemsize == 348


def _volume(unit="1/mm", shape=(5, 6, 7), seed=0) -> Volume:
    rng = np.random.default_rng(seed)
    if unit == "label":
        data = rng.integers(0, 6, size=shape).astype(np.int32)
    else:
        data = rng.uniform(0.0, 0.05, size=shape).astype(np.float32)
    return Volume(data, VolumeGrid(shape, SPACING, ORIGIN), unit)


def _nifti_header(path: Path) -> np.ndarray:
    opener = gzip.open if path.name.endswith(".gz") else open
    with opener(path, "rb") as handle:
        header = np.frombuffer(handle.read(348), dtype=NIFTI1_HEADER)[0]
    assert header["sizeof_hdr"] == 348
    return header


def _write_ras_nifti(path: Path, data_kji: np.ndarray, spacing, offset_ras) -> None:
    """A float32 NIfTI-1 as RAS tools write it: sform diag(+spacing), i toward the right."""
    header = np.zeros((), dtype=NIFTI1_HEADER)
    nz, ny, nx = data_kji.shape
    header["sizeof_hdr"] = 348
    header["dim"] = [3, nx, ny, nz, 1, 1, 1, 1]
    header["datatype"], header["bitpix"] = 16, 32
    header["pixdim"] = [1.0, *spacing, 0, 0, 0, 0]
    header["vox_offset"], header["scl_slope"], header["xyzt_units"] = 352, 1.0, 2
    header["descrip"] = b"written by another tool"
    header["sform_code"] = 1
    for row, name in enumerate(("srow_x", "srow_y", "srow_z")):
        header[name] = [
            spacing[0] * (row == 0),
            spacing[1] * (row == 1),
            spacing[2] * (row == 2),
            offset_ras[row],
        ]
    header["magic"] = b"n+1\x00"
    body = header.tobytes() + bytes(4) + data_kji.astype("<f4").tobytes()
    path.write_bytes(body)


# -- volumes ----------------------------------------------------------------------------------


@pytest.mark.parametrize("suffix", [".nii", ".nii.gz", ".mha", ".mhd"])
@pytest.mark.parametrize("unit", ["1/mm", "HU"])
def test_volume_round_trip_keeps_values_grid_and_unit(tmp_path, suffix, unit):
    volume = _volume(unit)
    path = write_volume(tmp_path / f"vol{suffix}", volume)
    back = read_volume(path)
    assert back.unit == unit
    assert back.data.dtype == np.float32
    np.testing.assert_array_equal(back.data, volume.data)
    assert back.grid.shape == volume.grid.shape
    np.testing.assert_allclose(back.grid.spacing_mm, SPACING, atol=1e-6)
    np.testing.assert_allclose(back.grid.origin_mm, ORIGIN, atol=1e-5)
    assert sitk.ReadImage(str(path)).GetPixelID() == sitk.sitkFloat32


@pytest.mark.parametrize("suffix", [".nii.gz", ".mha"])
@pytest.mark.parametrize(
    ("low", "high", "pixel_id"),
    [(0, 255, sitk.sitkUInt8), (-1, 5, sitk.sitkInt16), (0, 300, sitk.sitkInt16)],
)
def test_labels_are_stored_as_small_integers(tmp_path, suffix, low, high, pixel_id):
    volume = _volume("label")
    data = volume.data.copy()
    data[0, 0, 0], data[-1, -1, -1] = low, high
    path = write_volume(tmp_path / f"labels{suffix}", Volume(data, volume.grid, "label"))
    assert sitk.ReadImage(str(path)).GetPixelID() == pixel_id
    back = read_volume(path)
    assert back.unit == "label"
    assert np.issubdtype(back.data.dtype, np.integer)
    np.testing.assert_array_equal(back.data, data)


@pytest.mark.parametrize(("value", "match"), [(40000, "int16 range"), (1.5, "whole numbers")])
def test_labels_out_of_range_or_fractional_are_refused(tmp_path, value, match):
    volume = _volume("label")
    data = volume.data.astype(np.float64)
    data[1, 2, 3] = value
    with pytest.raises(ValueError, match=match):
        write_volume(tmp_path / "labels.mha", Volume(data, volume.grid, "label"))
    assert not (tmp_path / "labels.mha").exists()


@pytest.mark.parametrize("suffix", [".nii", ".nii.gz"])
def test_nifti_header_is_ras_with_unit_in_descrip(tmp_path, suffix):
    path = write_volume(tmp_path / f"vol{suffix}", _volume("HU"))
    header = _nifti_header(path)
    (sx, sy, sz), (ox, oy, oz) = SPACING, ORIGIN
    assert header["magic"] == b"n+1"  # "n+1\0": numpy strips trailing NULs
    assert header["sform_code"] > 0
    assert header["qform_code"] > 0
    np.testing.assert_allclose(header["srow_x"], [-sx, 0, 0, -ox], atol=1e-6)
    np.testing.assert_allclose(header["srow_y"], [0, -sy, 0, -oy], atol=1e-6)
    np.testing.assert_allclose(header["srow_z"], [0, 0, sz, oz], atol=1e-6)
    qoffset = [header["qoffset_x"], header["qoffset_y"], header["qoffset_z"]]
    np.testing.assert_allclose(qoffset, [-ox, -oy, oz], atol=1e-6)
    np.testing.assert_allclose(header["pixdim"][1:4], SPACING, atol=1e-6)
    assert list(header["dim"][:4]) == [3, 7, 6, 5]
    assert header["descrip"] == b"dualarm-cbct unit=HU"


def test_metaimage_header_states_unit_and_lps_placement(tmp_path):
    path = write_volume(tmp_path / "vol.mha", _volume("1/mm"))
    text = path.read_bytes().split(b"ElementDataFile")[0].decode()
    assert "ITK_FileNotes = dualarm-cbct unit=1/mm" in text
    assert "TransformMatrix = 1 0 0 0 1 0 0 0 1" in text
    assert "Offset = -10.25 20.5 30.75" in text


def test_ras_nifti_from_another_tool_is_reoriented_to_lps(tmp_path):
    data_kji = np.random.default_rng(1).normal(size=(4, 5, 6)).astype(np.float32)
    spacing, offset_ras = (0.5, 0.8, 1.5), (-20.0, 30.0, 40.0)
    path = tmp_path / "ras.nii"
    _write_ras_nifti(path, data_kji, spacing, offset_ras)
    volume = read_volume(path, unit="HU")
    # file voxel (i, j, k) sits at RAS (-20 + 0.5 i, 30 + 0.8 j, 40 + 1.5 k):
    # LPS x and y decrease with i and j, so both array axes flip.
    np.testing.assert_array_equal(volume.data, data_kji[:, ::-1, ::-1])
    np.testing.assert_allclose(volume.grid.spacing_mm, spacing, atol=1e-6)
    np.testing.assert_allclose(
        volume.grid.origin_mm, (20.0 - 5 * 0.5, -30.0 - 4 * 0.8, 40.0), atol=1e-5
    )
    assert volume.unit == "HU"


def test_signed_permutation_direction_keeps_world_positions(tmp_path):
    file_array = np.random.default_rng(2).normal(size=(6, 5, 4)).astype(np.float32)
    direction = np.array([[0, 0, -1], [-1, 0, 0], [0, 1, 0]], dtype=float)  # columns: i, j, k
    spacing, origin = np.array([0.5, 0.7, 1.1]), np.array([3.0, -4.0, 5.0])
    image = sitk.GetImageFromArray(file_array)
    image.SetSpacing(spacing.tolist())
    image.SetOrigin(origin.tolist())
    image.SetDirection(direction.ravel().tolist())
    path = tmp_path / "permuted.mha"
    sitk.WriteImage(image, str(path))

    volume = read_volume(path, unit="1/mm")
    assert volume.grid.shape == (5, 4, 6)
    np.testing.assert_allclose(volume.grid.spacing_mm, (1.1, 0.5, 0.7))
    k, j, i = np.indices(file_array.shape).reshape(3, -1)
    world = origin + (direction @ (spacing[:, None] * np.stack([i, j, k]))).T
    index = volume.grid.world_to_index(world)
    np.testing.assert_allclose(index, np.rint(index), atol=1e-9)
    ix, iy, iz = np.rint(index).astype(int).T
    np.testing.assert_array_equal(volume.data[iz, iy, ix], file_array[k, j, i])


def _oblique_image(values: np.ndarray) -> sitk.Image:
    """``values`` [k, j, i] on a grid tilted 30 deg about z and 20 deg about x (a gantry tilt)."""
    image = sitk.GetImageFromArray(values)
    rotation = Rotation.from_euler("zx", [30, 20], degrees=True).as_matrix()
    image.SetDirection(rotation.ravel().tolist())
    image.SetSpacing((0.8, 0.9, 1.5))
    image.SetOrigin((-7.0, 3.0, 11.0))
    return image


def test_an_oblique_volume_is_resampled_keeping_world_positions(tmp_path):
    """Trilinear interpolation reproduces a linear function exactly: inside the tilted grid's
    voxel centres every voxel holds the function at its own world position."""
    source = _oblique_image(np.zeros((12, 14, 16), np.float32))
    k, j, i = np.indices((12, 14, 16)).reshape(3, -1)
    direction = np.reshape(source.GetDirection(), (3, 3))
    spacing = np.array(source.GetSpacing())[:, None]
    world = (np.array(source.GetOrigin())[:, None] + direction @ (spacing * [i, j, k])).T
    gradient = np.array([0.3, -0.2, 0.5])
    values = (world @ gradient + 4.0).reshape(12, 14, 16).astype(np.float32)
    path = tmp_path / "oblique.mha"
    sitk.WriteImage(_oblique_image(values), str(path))
    volume = read_volume(path, unit="HU")
    assert volume.grid.spacing_mm == (0.8, 0.8, 0.8)
    zz, yy, xx = np.indices(volume.grid.shape).reshape(3, -1)
    centres = np.asarray(volume.grid.origin_mm) + 0.8 * np.stack([xx, yy, zz], axis=1)
    index = np.linalg.solve(direction, (centres - source.GetOrigin()).T).T / spacing.T
    inside = np.all((index >= -1e-6) & (index <= np.array(source.GetSize()) - 1 + 1e-6), axis=1)
    assert inside.sum() > 0.2 * inside.size
    expected = centres @ gradient + 4.0
    np.testing.assert_allclose(volume.data.ravel()[inside], expected[inside], atol=1e-3)
    assert volume.data.ravel()[~inside].min() == pytest.approx(values.min(), abs=1e-3)


def test_oblique_labels_are_resampled_nearest_onto_the_values_grid(tmp_path):
    labels = np.zeros((12, 14, 16), np.uint8)
    labels[3:9, 4:10, 5:12] = 3
    labels[5:7, 6:8, 7:9] = 5
    write = lambda name, a: sitk.WriteImage(_oblique_image(a), str(tmp_path / name))  # noqa: E731
    write("labels.mha", labels)
    write("values.mha", labels.astype(np.float32))
    read = read_volume(tmp_path / "labels.mha", unit="label")
    values = read_volume(tmp_path / "values.mha", unit="1/mm")
    assert read.grid == values.grid and read.data.dtype == np.uint8
    assert set(np.unique(read.data)) == {0, 3, 5}
    # the label volume of each label keeps its size within a voxel's worth of the boundary
    for label, voxels in ((3, 6 * 6 * 7), (5, 2 * 2 * 2)):
        source_mm3 = voxels * 0.8 * 0.9 * 1.5
        assert np.count_nonzero(read.data == label) * 0.8**3 == pytest.approx(
            source_mm3, rel=0.35 if label == 5 else 0.1
        )


def test_a_direction_that_is_not_a_rotation_is_refused_naming_the_file(tmp_path):
    image = sitk.GetImageFromArray(np.zeros((3, 4, 5), np.float32))
    image.SetDirection([1, 0.5, 0, 0, 1, 0, 0, 0, 1])
    path = tmp_path / "sheared.mha"
    sitk.WriteImage(image, str(path))
    with pytest.raises(ValueError, match=r"sheared.mha: image direction .* is not a rotation"):
        read_volume(path, unit="1/mm")
    # found by the fuzz tests: ITK's reader never returned from this header
    huge = tmp_path / "huge.mha"
    huge.write_bytes(
        path.read_bytes().replace(b"TransformMatrix = 1 0 0 0.5", b"TransformMatrix = 1 0 0 1e308")
    )
    with pytest.raises(ValueError, match=r"huge.mha: image direction .* is not a rotation"):
        read_volume(huge, unit="1/mm")


def test_unit_missing_or_conflicting_is_refused(tmp_path):
    path = tmp_path / "plain.nii.gz"
    sitk.WriteImage(sitk.GetImageFromArray(np.zeros((3, 4, 5), np.float32)), str(path))
    with pytest.raises(ValueError, match="does not state its unit"):
        read_volume(path)
    assert read_volume(path, unit="HU").unit == "HU"
    stated = write_volume(tmp_path / "stated.nii.gz", _volume("1/mm"))
    with pytest.raises(ValueError, match="states unit '1/mm', but 'HU'"):
        read_volume(stated, unit="HU")


def test_missing_file_raises_file_not_found(tmp_path):
    path = tmp_path / "absent.nii.gz"
    with pytest.raises(FileNotFoundError, match=r"absent\.nii\.gz: no such file"):
        read_volume(path)
    with pytest.raises(FileNotFoundError, match=r"absent\.mha: no such file"):
        read_projections(tmp_path / "absent.mha")


@pytest.mark.parametrize("name", ["garbage.mha", "garbage.nii", "garbage.nii.gz"])
def test_garbage_bytes_raise_image_file_error(tmp_path, name):
    path = tmp_path / name
    path.write_bytes(np.random.default_rng(3).bytes(2000))
    with pytest.raises(ImageFileError, match=f"{name}: not a readable image") as info:
        read_volume(path)
    assert isinstance(info.value, OSError)
    assert not isinstance(info.value.__cause__, type(None))


@pytest.mark.parametrize(
    ("name", "data_file"),
    [("v.mha", "v.mha"), ("v.mhd", "v.raw"), ("v.nii", "v.nii"), ("v.nii.gz", "v.nii.gz")],
)
def test_truncated_file_raises_image_file_error(tmp_path, name, data_file):
    volume = Volume(np.ones((20, 30, 40), np.float32), VolumeGrid((20, 30, 40), SPACING, ORIGIN))
    write_volume(tmp_path / name, volume)
    target = tmp_path / data_file
    target.write_bytes(target.read_bytes()[: target.stat().st_size * 2 // 3])
    with pytest.raises(ImageFileError, match=rf"{name}: .*(truncated|not a readable image)"):
        read_volume(tmp_path / name)


def test_nii_gz_beside_nii_is_refused(tmp_path):
    # ITK's NIfTI reader asked for a.nii.gz silently reads a.nii when both exist
    write_volume(tmp_path / "a.nii", _volume("HU"))
    with pytest.raises(ValueError, match=r"a\.nii\.gz: a\.nii exists beside it"):
        write_volume(tmp_path / "a.nii.gz", _volume("1/mm"))
    blank = sitk.GetImageFromArray(np.zeros((3, 4, 5), np.float32))
    sitk.WriteImage(blank, str(tmp_path / "a.nii.gz"))
    with pytest.raises(ValueError, match=r"a\.nii\.gz: a\.nii exists beside it"):
        read_volume(tmp_path / "a.nii.gz")


def test_two_dimensional_image_is_not_a_volume(tmp_path):
    path = tmp_path / "flat.mha"
    sitk.WriteImage(sitk.GetImageFromArray(np.zeros((4, 5), np.float32)), str(path))
    with pytest.raises(ValueError, match=r"flat.mha: expected a 3-D image, got 2-D"):
        read_volume(path, unit="1/mm")
    with pytest.raises(ValueError, match=r"flat.mha: expected a 3-D image"):
        read_projections(path)


def test_nan_volume_is_refused_before_writing(tmp_path):
    volume = _volume()
    data = volume.data.copy()
    data[2, 3, 4] = np.nan
    data[0, 0, 0] = np.inf
    path = tmp_path / "nan.nii.gz"
    with pytest.raises(ValueError, match=r"nan.nii.gz: volume data contain 2 non-finite"):
        write_volume(path, Volume(data, volume.grid))
    assert not path.exists()


def test_bad_suffix_and_missing_folder_are_refused(tmp_path):
    with pytest.raises(ValueError, match=r"vol.png: unsupported volume file type"):
        write_volume(tmp_path / "vol.png", _volume())
    with pytest.raises(FileNotFoundError, match=r"output folder .*nowhere does not exist"):
        write_volume(tmp_path / "nowhere" / "vol.mha", _volume())


# -- projection stacks ------------------------------------------------------------------------


def _projections(views=3, rows=4, cols=6) -> np.ndarray:
    return np.random.default_rng(4).uniform(0, 5, (views, rows, cols)).astype(np.float32)


def test_projection_round_trip_with_centred_default_origin(tmp_path):
    data = _projections()
    path = write_projections(tmp_path / "proj.mha", data, pixel_pitch_mm=0.2)
    stack = read_projections(path)
    np.testing.assert_array_equal(stack.data, data)
    assert stack.pixel_pitch_mm == (0.2, 0.2)
    np.testing.assert_allclose(stack.header.origin_mm, (-0.5, -0.3), atol=1e-12)
    assert (stack.header.rows, stack.header.cols) == (4, 6)
    assert stack.header.direction == ((1.0, 0.0), (0.0, 1.0))


def test_projection_explicit_origin_and_mhd(tmp_path):
    path = write_projections(tmp_path / "p.mhd", _projections(), 0.5, origin_uv_mm=(-7.0, 2.5))
    stack = read_projections(path)
    assert stack.header.origin_mm == (-7.0, 2.5)
    assert stack.pixel_pitch_mm == (0.5, 0.5)
    with pytest.raises(ValueError, match="data must be float32"):
        ProjectionStack(stack.data.astype(np.float64), stack.header)


@pytest.mark.filterwarnings("ignore::DeprecationWarning")  # SWIG types in itk's wrapping
def test_rtk_reads_our_projection_stack(tmp_path):
    itk = pytest.importorskip("itk")
    data = _projections(views=2, rows=5, cols=7)
    path = write_projections(tmp_path / "proj.mha", data, pixel_pitch_mm=0.25)
    reader = itk.RTK.ProjectionsReader[itk.Image[itk.F, 3]].New()
    reader.SetFileNames([str(path)])
    reader.Update()
    image = reader.GetOutput()
    assert list(itk.size(image)) == [7, 5, 2]  # (cols, rows, views)
    np.testing.assert_allclose(list(image.GetSpacing()), [0.25, 0.25, 1.0])
    np.testing.assert_allclose(list(image.GetOrigin()), [-0.75, -0.5, 0.0])
    np.testing.assert_array_equal(itk.array_from_image(image), data)


@pytest.mark.parametrize(
    ("shape", "dtype", "pitch", "origin"),
    [
        ((3, 4, 6), np.float32, 0.2, None),
        ((1, 1, 5), np.float64, 0.776, None),  # one row: a centred v origin of -0.0
        ((2, 3, 3), np.float32, 1 / 3, (-7.123456789012345e-7, 2.5e6)),
        ((1, 2, 2), np.int16, 123.456, (0.0, -0.0)),
    ],
)
def test_encoded_projections_are_the_written_file(tmp_path, shape, dtype, pitch, origin):
    """The in-memory .mha (header, then pixels) is SimpleITK's file byte for byte, and the
    pixels of a float32 stack are not copied."""
    data = (np.random.default_rng(2).normal(size=shape) * 100).astype(dtype)
    path = write_projections(tmp_path / "p.mha", data, pitch, origin_uv_mm=origin)
    header, pixels = encode_projections(data, pitch, origin)
    assert header + pixels.tobytes() == path.read_bytes()
    assert (pixels is data) == (dtype is np.float32)


@pytest.mark.parametrize("pitch", [0.0, -0.1, float("nan")])
def test_non_positive_pitch_is_refused(tmp_path, pitch):
    with pytest.raises(ValueError, match=r"p.mha: pixel_pitch_mm must be a finite pitch > 0"):
        write_projections(tmp_path / "p.mha", _projections(), pitch)


def test_bad_projection_arrays_are_refused(tmp_path):
    data = _projections()
    data[1, 2, 3] = np.nan
    with pytest.raises(ValueError, match=r"p.mha: projections contain 1 non-finite"):
        write_projections(tmp_path / "p.mha", data, 0.2)
    with pytest.raises(ValueError, match=r"shape \(4, 6\)"):
        write_projections(tmp_path / "p.mha", _projections()[0], 0.2)
    with pytest.raises(ValueError, match="unsupported projection stack file type"):
        write_projections(tmp_path / "p.nii.gz", _projections(), 0.2)
    assert not (tmp_path / "p.mha").exists()


# -- DICOM ------------------------------------------------------------------------------------


def _dicom_volume() -> Volume:
    rng = np.random.default_rng(5)
    data = rng.uniform(0.0, 0.05, size=(4, 6, 5))
    return Volume(data, VolumeGrid((4, 6, 5), (0.5, 0.8, 1.25), (-12.3, 45.6, -7.8)), "1/mm")


def _tags(path: Path) -> sitk.ImageFileReader:
    reader = sitk.ImageFileReader()
    reader.SetFileName(str(path))
    reader.ReadImageInformation()
    return reader


def test_dicom_series_reads_back_same_grid_and_hu(tmp_path):
    volume, mu_water = _dicom_volume(), 0.02
    paths = write_dicom_series(tmp_path / "dcm", volume, mu_water, patient_id="P001")
    assert len(paths) == 4

    names = sitk.ImageSeriesReader.GetGDCMSeriesFileNames(str(tmp_path / "dcm"))
    assert [Path(n) for n in names] == paths
    series = sitk.ImageSeriesReader()
    series.SetFileNames(names)
    image = series.Execute()
    np.testing.assert_allclose(image.GetSpacing(), (0.5, 0.8, 1.25), atol=1e-6)
    np.testing.assert_allclose(image.GetOrigin(), (-12.3, 45.6, -7.8), atol=1e-6)
    np.testing.assert_allclose(image.GetDirection(), np.eye(3).ravel(), atol=1e-9)
    expected_hu = 1000.0 * (volume.data - mu_water) / mu_water  # -1000 .. +1500 HU
    error = sitk.GetArrayFromImage(image).astype(np.float64) - expected_hu
    assert np.abs(error).max() <= 0.5 + 1e-9  # slope 1 HU: rounding error only


def test_dicom_tags(tmp_path):
    paths = write_dicom_series(
        tmp_path / "dcm", _dicom_volume(), 0.02, series_description="knee", patient_id="P001"
    )
    tags = [_tags(p) for p in paths]
    first = tags[0]
    assert first.GetMetaData("0008|0016") == CT_IMAGE_STORAGE
    assert first.GetMetaData("0008|0060").strip() == "CT"
    assert first.GetMetaData("0008|103e").strip() == "knee"
    assert first.GetMetaData("0010|0020").strip() == "P001"
    assert first.GetMetaData("0028|1054").strip() == "HU"
    assert first.GetMetaData("0020|0037").strip() == "1\\0\\0\\0\\1\\0"
    assert [float(v) for v in first.GetMetaData("0028|0030").split("\\")] == [0.8, 0.5]
    assert float(first.GetMetaData("0018|0050")) == 1.25
    assert float(first.GetMetaData("0018|0088")) == 1.25
    assert float(first.GetMetaData("0028|1053")) == 1.0
    assert float(first.GetMetaData("0028|1052")) == 0.0
    assert [int(t.GetMetaData("0020|0013")) for t in tags] == [1, 2, 3, 4]
    positions = [[float(v) for v in t.GetMetaData("0020|0032").split("\\")] for t in tags]
    np.testing.assert_allclose(
        positions, [[-12.3, 45.6, -7.8 + 1.25 * k] for k in range(4)], atol=1e-9
    )
    assert len({t.GetMetaData("0008|0018") for t in tags}) == 4
    for key in ("0020|000d", "0020|000e", "0020|0052"):
        assert len({t.GetMetaData(key) for t in tags}) == 1
    # a second series, written after this process read DICOM files (GDCM keeps state)
    again = [_tags(p) for p in write_dicom_series(tmp_path / "again", _dicom_volume(), 0.02)]
    assert again[0].GetMetaData("0020|000e") != first.GetMetaData("0020|000e")
    assert [float(t.GetMetaData("0018|0088")) for t in again] == [1.25] * 4


def test_dicom_hu_volume_written_as_is_with_wide_range(tmp_path):
    volume = _dicom_volume()
    hu = np.linspace(-1000.0, 99000.0, volume.data.size).reshape(volume.data.shape)
    paths = write_dicom_series(tmp_path / "dcm", Volume(hu, volume.grid, "HU"), 0.02)
    slope, intercept = rescale_for(-1000.0, 99000.0)
    assert (slope, intercept) == (2.0, 49000.0)
    assert float(_tags(paths[0]).GetMetaData("0028|1053")) == 2.0
    series = sitk.ImageSeriesReader()
    series.SetFileNames([str(p) for p in paths])
    back = sitk.GetArrayFromImage(series.Execute()).astype(np.float64)
    assert np.abs(back - hu).max() <= 1.0 + 1e-9  # slope 2 HU: error <= slope / 2


def test_rescale_keeps_stored_values_in_int16():
    for low, high in [(-1024.0, 3071.0), (-40000.0, 20000.0), (-5e5, 7e5), (100.0, 100.0)]:
        slope, intercept = rescale_for(low, high)
        stored = np.rint((np.array([low, high]) - intercept) / slope)
        assert np.all(np.abs(stored) <= 32767)
    assert rescale_for(-1024.0, 3071.0) == (1.0, 0.0)


def test_dicom_refuses_non_empty_folder_and_labels(tmp_path):
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "x.txt").write_text("x")
    with pytest.raises(FileExistsError, match="busy: folder is not empty"):
        write_dicom_series(tmp_path / "busy", _dicom_volume(), 0.02)
    labels = _volume("label")
    with pytest.raises(ValueError, match="label volumes cannot be written"):
        write_dicom_series(tmp_path / "labels", labels, 0.02)
    with pytest.raises(ValueError, match="mu_water_per_mm must be finite and > 0"):
        write_dicom_series(tmp_path / "mu", _dicom_volume(), 0.0)
    assert not (tmp_path / "labels").exists() and not (tmp_path / "mu").exists()


# -- preview ----------------------------------------------------------------------------------


def _blob_volume() -> tuple[Volume, tuple[float, float, float]]:
    """A bright cube at +x (patient left), -y (anterior), +z (superior) of the grid centre."""
    grid = VolumeGrid.centered((28, 24, 20), (1.0, 1.0, 2.0))
    data = np.zeros(grid.shape, np.float32)
    data[14:17, 5:8, 20:23] = 1.0  # z 14..16, y 5..7, x 20..22
    return Volume(data, grid), tuple(grid.index_to_world((21, 6, 15)))


def test_slices_follow_radiological_orientation():
    volume, blob = _blob_volume()
    panels = {p.name: p for p in orthogonal_slices(volume, point_mm=blob)}
    expected = {  # (horizontal, vertical) world coordinate of the blob in each panel
        "axial": (blob[0], blob[1]),
        "coronal": (blob[0], blob[2]),
        "sagittal": (blob[1], blob[2]),
    }
    for name, (h, v) in expected.items():
        panel = panels[name]
        left, right, bottom, top = panel.extent_mm
        rows, cols = panel.image.shape
        row, col = np.argwhere(panel.image == panel.image.max()).mean(axis=0)
        np.testing.assert_allclose(left + (col + 0.5) * (right - left) / cols, h, atol=1e-9)
        np.testing.assert_allclose(top + (row + 0.5) * (bottom - top) / rows, v, atol=1e-9)
    assert panels["axial"].extent_mm[3] < panels["axial"].extent_mm[2]  # anterior (-y) on top
    assert panels["sagittal"].extent_mm[0] < panels["sagittal"].extent_mm[1]  # anterior left
    assert panels["coronal"].image.shape == (20, 28)


def test_rendered_png_shows_blob_left_top_as_expected(tmp_path):
    volume, blob = _blob_volume()
    fig = render_orthogonal_slices(volume, title="blob", window=(0.0, 1.0), point_mm=blob)
    buffer = std_io.BytesIO()
    fig.savefig(buffer, format="png", dpi=DPI)
    pixels = mpimg.imread(std_io.BytesIO(buffer.getvalue()))[..., :3].mean(axis=2)
    height = pixels.shape[0]
    world = {
        "axial": (blob[0], blob[1]),
        "coronal": (blob[0], blob[2]),
        "sagittal": (blob[1], blob[2]),
    }
    # (horizontal, vertical) half where the blob must show: +1 right/top, -1 left/bottom
    halves = {"axial": (1, 1), "coronal": (1, 1), "sagittal": (-1, 1)}
    for ax, name in zip(fig.axes[:3], ("axial", "coronal", "sagittal"), strict=True):
        x, y = ax.transData.transform(world[name])
        box = ax.get_window_extent()
        cx, cy = (box.x0 + box.x1) / 2, (box.y0 + box.y1) / 2
        assert np.sign(x - cx) == halves[name][0] and np.sign(y - cy) == halves[name][1]
        assert pixels[int(height - y), int(x)] > 0.9  # the blob is white there
        assert pixels[int(height - (2 * cy - y)), int(2 * cx - x)] < 0.1  # mirror is black
    assert "linear attenuation (1/mm)" in fig.axes[3].get_ylabel()


def test_save_writes_png_of_expected_size(tmp_path):
    volume, _ = _blob_volume()
    path = save_orthogonal_slices(volume, tmp_path / "preview.png", title="knee")
    image = mpimg.imread(path)
    assert image.shape[:2] == (round(FIGSIZE_IN[1] * DPI), round(FIGSIZE_IN[0] * DPI))
    with pytest.raises(ValueError, match="outside the volume's grid"):
        save_orthogonal_slices(volume, tmp_path / "x.png", point_mm=(500.0, 0.0, 0.0))

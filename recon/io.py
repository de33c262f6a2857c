"""Volume and projection-stack files: NIfTI (.nii, .nii.gz) and MetaImage (.mha, .mhd).

This module is the file boundary of DESIGN.md. In memory, volumes live in the world frame
(DICOM/ITK LPS) on axis-aligned grids (:class:`~recon.volume.Volume`). On disk, NIfTI stores
RAS: SimpleITK's NIfTI writer and reader negate x and y (``x_RAS = -x_LPS``,
``y_RAS = -y_LPS``) in the sform/qform, so LPS never leaks into RAS or back; the tests check
the written header bytes. A file whose axes are a signed permutation of the world axes (e.g. a
NIfTI saved in RAS orientation by another tool) is reoriented on read by flipping/transposing
the array, so the returned grid has identity direction and every voxel keeps its world
position. Oblique files are refused.

The volume's unit is stored in ITK's ``ITK_FileNotes`` metadata key: MetaImage writes it as a
header line ``ITK_FileNotes = dualarm-cbct unit=1/mm``, and ITK's NIfTI writer puts it in the
80-character ``descrip`` field (ITK ignores ``descrip`` and ``intent_name`` keys on write).

Projection stacks (line integrals, float32, indexed ``(views, rows, cols)``) are written as
MetaImage 3-D images the way RTK reads them: size (cols, rows, views), spacing
(pitch_u, pitch_v, 1) and origin (u0, v0, 0), where (u0, v0) mm is the centre of pixel
(row 0, col 0) in the detector plane. RTK places its detector frame origin on the panel's
centre for centred panels, hence the default origin ``u0 = -(cols - 1) / 2 * pitch``,
``v0 = -(rows - 1) / 2 * pitch``. Stacks from elsewhere are read with whatever origin,
spacing and in-plane direction their header states (:class:`~recon.rtk_xml.PanelHeader`:
RTK's default origin is (0, 0), not centred), never assuming a centred panel. NIfTI is
refused for projections: its RAS flip would negate the (u, v) origin.

Every failure raises before any long work, with the file path and what is wrong:
:class:`FileNotFoundError` for a missing file, :class:`ImageFileError` (an :class:`OSError`)
for a file that cannot be read or is truncated, :class:`ValueError` for valid files with the
wrong content and for bad arguments.
"""

from __future__ import annotations

import gzip
import math
import re
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from recon.rtk_xml import PanelHeader, centered_origin_uv_mm
from recon.volume import Unit, Volume, VolumeGrid

VOLUME_SUFFIXES = (".nii.gz", ".nii", ".mha", ".mhd")
"""File name endings :func:`write_volume` and :func:`read_volume` accept."""

PROJECTION_SUFFIXES = (".mha", ".mhd")
"""File name endings :func:`write_projections` and :func:`read_projections` accept."""

NOTES_KEY = "ITK_FileNotes"
"""ITK metadata key holding the unit; NIfTI's ``descrip`` field, a MetaImage header line."""

_INTEGER_PIXEL_IDS = frozenset(
    {
        sitk.sitkUInt8,
        sitk.sitkInt8,
        sitk.sitkUInt16,
        sitk.sitkInt16,
        sitk.sitkUInt32,
        sitk.sitkInt32,
        sitk.sitkUInt64,
        sitk.sitkInt64,
    }
)
_UNIT_RE = re.compile(r"\bunit=(1/mm|HU|label)(?:\s|$)")
_ORTHONORMAL_ATOL = 1e-4
"""Largest |D^T D - I| entry of an image direction taken as a rotation (DICOM's orientation
cosines carry about six digits)."""
_DIRECTION_ATOL = 1e-4
_VIEWS_PER_READ = 32
_GZIP_CHUNK_BYTES = 1 << 22
_ITK_CLASS_PREFIX = re.compile(r"^\s*\w+\(0x[0-9a-fA-F]+\):\s*")


class ImageFileError(OSError):
    """A file that exists but cannot be read as an image: garbage, truncated, unreadable."""


# -- volumes ----------------------------------------------------------------------------------


def write_volume(path: str | Path, volume: Volume) -> Path:
    """Write a volume to ``.nii``, ``.nii.gz``, ``.mha`` or ``.mhd``.

    Attenuation (1/mm) and HU volumes are stored as float32; label volumes as uint8 when
    their values fit in 0..255, else int16. The world placement (LPS, identity direction) and
    the unit are stored with the data.

    Args:
        path: output file; its ending chooses the format. Overwritten if it exists.
        volume: values indexed [z, y, x] on an axis-aligned LPS grid.

    Returns:
        The path written.

    Raises:
        ValueError: unsupported ending, non-finite values, labels that are not integers in
            the int16 range, ``x.nii.gz`` asked for beside an existing ``x.nii``.
        FileNotFoundError: the output folder does not exist.
        ImageFileError: SimpleITK could not write the file.
    """
    path = _check_suffix(Path(path), VOLUME_SUFFIXES, "volume")
    _check_parent(path)
    data = _storage_array(volume, path)
    image = sitk.GetImageFromArray(data)
    image.SetSpacing(volume.grid.spacing_mm)
    image.SetOrigin(volume.grid.origin_mm)
    image.SetMetaData(NOTES_KEY, f"dualarm-cbct unit={volume.unit}")
    _write_image(image, path)
    return path


def read_volume(path: str | Path, unit: Unit | None = None) -> Volume:
    """Read a 3-D volume from ``.nii``, ``.nii.gz``, ``.mha`` or ``.mhd``.

    Files whose axes are a signed permutation of the LPS axes are reoriented (array flipped
    and transposed) so the returned grid has identity direction and the same world position
    for every voxel; oblique ones are resampled onto an axis-aligned grid
    (:func:`identity_oriented`).

    Args:
        path: the file.
        unit: the unit to assume when the file does not state one (files from other tools).
            When the file states a unit, ``unit`` must be None or the same.

    Returns:
        The volume: float32 values for 1/mm and HU, the stored integer type for labels.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ImageFileError: not an image, truncated, or unreadable.
        ValueError: not a scalar 3-D image, a direction that is not a rotation, a missing or
            conflicting unit, or a label file with non-integer pixels.
    """
    path = _check_suffix(Path(path), VOLUME_SUFFIXES, "volume")
    reader = _open_image(path)
    file_unit = _unit_from_notes(reader)
    resolved = _resolve_unit(path, file_unit, unit)
    if resolved == "label" and reader.GetPixelID() not in _INTEGER_PIXEL_IDS:
        raise ValueError(
            f"{path}: label volume must have integer pixels, "
            f"got {sitk.GetPixelIDValueAsString(reader.GetPixelID())}"
        )
    data, grid = identity_oriented(_execute(reader, path), path, label=resolved == "label")
    if resolved != "label":
        data = data.astype(np.float32, copy=False)
    return Volume(data=data, grid=grid, unit=resolved)


def volume_unit_note(path: str | Path) -> Unit | None:
    """The unit a volume file states (its ``ITK_FileNotes``), None when it states none; reads
    the header only."""
    path = _check_suffix(Path(path), VOLUME_SUFFIXES, "volume")
    return _unit_from_notes(_open_image(path))


def identity_oriented(
    image: sitk.Image, path: Path, label: bool = False
) -> tuple[np.ndarray, VolumeGrid]:
    """A 3-D SimpleITK image's array [z, y, x] and grid with identity direction: files whose
    axes are a signed permutation of the LPS axes are flipped and transposed (every voxel keeps
    its world position); oblique ones (a tilted gantry, an oblique acquisition) are resampled
    onto the axis-aligned grid that covers their voxel centres, cubic voxels of their finest
    spacing: trilinear for values (outside: the image's minimum, air), nearest for ``label``
    volumes (outside: 0). Two files on the same oblique grid land on the same grid."""
    direction = np.reshape(image.GetDirection(), (3, 3))
    _check_rotation(direction, path)
    if not _is_signed_permutation(direction):
        image = _axis_aligned(image, label)
    signed_perm = _signed_permutation(np.reshape(image.GetDirection(), (3, 3)), path)
    data, spacing, origin = _reorient_to_identity(
        sitk.GetArrayFromImage(image), image.GetSpacing(), image.GetOrigin(), signed_perm
    )
    return data, VolumeGrid(data.shape, spacing, origin)


def _storage_array(volume: Volume, path: Path) -> np.ndarray:
    """The array to write: float32 for 1/mm and HU, uint8 or int16 for labels."""
    data = np.asarray(volume.data)
    if not np.issubdtype(data.dtype, np.number) and data.dtype != np.bool_:
        raise ValueError(f"{path}: volume data must be numeric, got dtype {data.dtype}")
    if volume.unit != "label":
        _check_finite(data, path, "volume data")
        return data.astype(np.float32)
    _check_finite(data, path, "label data")
    if not np.array_equal(data, np.round(data)):
        raise ValueError(f"{path}: label data must be whole numbers, got fractional values")
    low, high = float(data.min()), float(data.max())
    if low >= 0 and high <= 255:
        return data.astype(np.uint8)
    info = np.iinfo(np.int16)
    if low < info.min or high > info.max:
        raise ValueError(f"{path}: labels must lie within the int16 range, got {low:g}..{high:g}")
    return data.astype(np.int16)


def _unit_from_notes(reader: sitk.ImageFileReader) -> Unit | None:
    if not reader.HasMetaDataKey(NOTES_KEY):
        return None
    match = _UNIT_RE.search(reader.GetMetaData(NOTES_KEY))
    return match.group(1) if match else None


def _resolve_unit(path: Path, file_unit: Unit | None, unit: Unit | None) -> Unit:
    if file_unit is None and unit is None:
        raise ValueError(
            f"{path}: the file does not state its unit ({NOTES_KEY} has no 'unit=...'); "
            "pass unit='1/mm', 'HU' or 'label'"
        )
    if file_unit is not None and unit is not None and unit != file_unit:
        raise ValueError(f"{path}: the file states unit {file_unit!r}, but {unit!r} was asked")
    return file_unit or unit


def _reorient_to_identity(
    array: np.ndarray,
    spacing: Sequence[float],
    origin: Sequence[float],
    signed_perm: np.ndarray,
) -> tuple[np.ndarray, tuple[float, ...], tuple[float, ...]]:
    """Flip and transpose an ITK array [k, j, i] so its direction becomes the identity.

    Args:
        array: the image as SimpleITK returns it, indexed [k, j, i].
        spacing, origin: the image's spacing (i, j, k) and origin (LPS) in mm.
        signed_perm: its direction, a 3x3 signed permutation (columns: axes i, j, k in LPS).

    Returns:
        The array indexed [z, y, x], spacing (sx, sy, sz) mm and the world position (x, y, z)
        mm of the new voxel [0, 0, 0].
    """
    world_axis = np.argmax(np.abs(signed_perm), axis=0)  # world axis of each file axis
    sign = signed_perm[world_axis, np.arange(3)]
    size = np.array(array.shape[::-1])
    corner = np.where(sign < 0, size - 1, 0)
    new_origin = np.asarray(origin) + signed_perm @ (np.asarray(spacing) * corner)
    flipped = np.flip(array, axis=[2 - a for a in range(3) if sign[a] < 0])
    axes = [0, 0, 0]
    new_spacing = [0.0, 0.0, 0.0]
    for a in range(3):
        axes[2 - world_axis[a]] = 2 - a
        new_spacing[world_axis[a]] = float(spacing[a])
    data = np.ascontiguousarray(np.transpose(flipped, axes))
    return data, tuple(new_spacing), tuple(float(x) for x in new_origin)


def _is_signed_permutation(direction: np.ndarray) -> bool:
    rounded = np.round(direction)
    return bool(
        np.all(np.abs(direction - rounded) <= _DIRECTION_ATOL)
        and np.all(np.abs(rounded).sum(axis=0) == 1)
        and np.all(np.abs(rounded).sum(axis=1) == 1)
    )


def _signed_permutation(direction: np.ndarray, path: Path) -> np.ndarray:
    """The signed permutation matrix ``direction`` is (within tolerance), else ValueError."""
    if not _is_signed_permutation(direction):
        raise ValueError(
            f"{path}: image direction {np.round(direction, 6).tolist()} is not axis-aligned"
        )
    return np.round(direction)


def _check_rotation(direction: np.ndarray, path: Path) -> None:
    """ValueError naming ``path`` unless the direction's columns are orthonormal."""
    error = float(np.abs(direction.T @ direction - np.eye(3)).max())
    if not np.all(np.isfinite(direction)) or error > _ORTHONORMAL_ATOL:
        raise ValueError(
            f"{path}: image direction {np.round(direction, 6).tolist()} (columns are the "
            f"file's axes in LPS) is not a rotation (|D^T D - I| = {error:.2g}, tolerance "
            f"{_ORTHONORMAL_ATOL:g})"
        )


def _axis_aligned(image: sitk.Image, label: bool) -> sitk.Image:
    """An oblique image resampled onto the identity-direction grid covering its voxel centres
    (cubic voxels of its finest spacing): linear for values, nearest for labels."""
    size = np.array(image.GetSize())
    corners = np.array(
        [
            image.TransformContinuousIndexToPhysicalPoint([float(c) for c in corner])
            for corner in np.stack(np.meshgrid(*([0, n - 1] for n in size)), -1).reshape(-1, 3)
        ]
    )
    spacing = float(min(image.GetSpacing()))
    low, high = corners.min(axis=0), corners.max(axis=0)
    shape = np.floor((high - low) / spacing + 1e-6).astype(int) + 1
    if label:
        interpolator, pixel, outside = sitk.sitkNearestNeighbor, image.GetPixelID(), 0.0
    else:
        interpolator, pixel = sitk.sitkLinear, sitk.sitkFloat32
        outside = float(sitk.GetArrayViewFromImage(image).min())
    return sitk.Resample(
        image,
        [int(n) for n in shape],
        sitk.Transform(),
        interpolator,
        low.tolist(),
        [spacing] * 3,
        np.eye(3).ravel().tolist(),
        outside,
        pixel,
    )


# -- projection stacks ------------------------------------------------------------------------


@dataclass(frozen=True)
class ProjectionStack:
    """Projections as read from a file.

    Attributes:
        data: line integrals -ln(I/I0), float32, shape (views, rows, cols), indexed
            [view, v, u].
        header: where the pixels lie in RTK's projection plane (origin, spacing, direction).
    """

    data: np.ndarray
    header: PanelHeader

    def __post_init__(self) -> None:
        if self.data.ndim != 3 or self.data.dtype != np.float32:
            raise ValueError(
                f"data must be float32 (views, rows, cols), got {self.data.dtype} "
                f"of shape {self.data.shape}"
            )

    @property
    def pixel_pitch_mm(self) -> tuple[float, float]:
        """Pixel pitch (u, v) = (along columns, along rows), mm."""
        return self.header.spacing_mm


def write_projections(
    path: str | Path,
    projections: np.ndarray,
    pixel_pitch_mm: float,
    origin_uv_mm: tuple[float, float] | None = None,
) -> Path:
    """Write a projection stack as an RTK-readable MetaImage (``.mha`` or ``.mhd``).

    Args:
        path: output file. Overwritten if it exists.
        projections: line integrals, shape (views, rows, cols); stored as float32.
        pixel_pitch_mm: square pixel pitch, mm, > 0.
        origin_uv_mm: (u, v) mm of the centre of pixel (row 0, col 0). Default: the panel
            centred on (0, 0), i.e. ``(-(cols - 1) / 2 * pitch, -(rows - 1) / 2 * pitch)``.

    Returns:
        The path written.

    Raises:
        ValueError: bad ending, shape, pitch, origin, or non-finite values.
        FileNotFoundError: the output folder does not exist.
        ImageFileError: SimpleITK could not write the file.
    """
    path = _check_suffix(Path(path), PROJECTION_SUFFIXES, "projection stack")
    _check_parent(path)
    data, pitch, origin = _checked_projections(projections, pixel_pitch_mm, origin_uv_mm, path)
    image = sitk.GetImageFromArray(data)
    image.SetSpacing((pitch, pitch, 1.0))
    image.SetOrigin((float(origin[0]), float(origin[1]), 0.0))
    _write_image(image, path)
    return path


def encode_projections(
    projections: np.ndarray,
    pixel_pitch_mm: float,
    origin_uv_mm: tuple[float, float] | None = None,
) -> tuple[bytes, np.ndarray]:
    """The ``.mha`` file :func:`write_projections` writes, in memory: its header and its
    pixels, to be hashed and written without a round trip through a file.

    Args: as :func:`write_projections`.

    Returns:
        The header (ASCII) and the pixels, float32 little-endian and C-contiguous (the input
        itself when it is such an array, not a copy); the file is the one after the other,
        byte for byte what SimpleITK writes.

    Raises:
        ValueError: bad shape, pitch, origin, or non-finite values.
    """
    data, pitch, origin = _checked_projections(
        projections, pixel_pitch_mm, origin_uv_mm, "projections"
    )
    views, rows, cols = data.shape

    def word(x: float) -> str:  # MetaIO's number format: 17 significant digits, no "-0"
        return f"{x + 0.0:.17g}"

    header = (
        "ObjectType = Image\nNDims = 3\nBinaryData = True\nBinaryDataByteOrderMSB = False\n"
        "CompressedData = False\nTransformMatrix = 1 0 0 0 1 0 0 0 1\n"
        f"Offset = {word(origin[0])} {word(origin[1])} 0\nCenterOfRotation = 0 0 0\n"
        f"AnatomicalOrientation = RAI\nElementSpacing = {word(pitch)} {word(pitch)} 1\n"
        f"DimSize = {cols} {rows} {views}\nElementType = MET_FLOAT\nElementDataFile = LOCAL\n"
    )
    return header.encode("ascii"), data


def _checked_projections(
    projections: np.ndarray,
    pixel_pitch_mm: float,
    origin_uv_mm: tuple[float, float] | None,
    name: Path | str,
) -> tuple[np.ndarray, float, np.ndarray]:
    """The stack as C-contiguous little-endian float32 (views, rows, cols), the pitch (mm) and
    the (u, v) origin (mm) after the checks of :func:`write_projections`."""
    pitch = float(pixel_pitch_mm)
    if not (math.isfinite(pitch) and pitch > 0):
        raise ValueError(f"{name}: pixel_pitch_mm must be a finite pitch > 0 mm, got {pitch!r}")
    data = np.asarray(projections)
    if data.ndim != 3 or min(data.shape) == 0:
        raise ValueError(
            f"{name}: projections must be a non-empty (views, rows, cols) array, "
            f"got shape {data.shape}"
        )
    if not (np.issubdtype(data.dtype, np.integer) or np.issubdtype(data.dtype, np.floating)):
        raise ValueError(f"{name}: projections must be real numbers, got dtype {data.dtype}")
    _check_finite(data, name, "projections")
    _, rows, cols = data.shape
    if origin_uv_mm is None:
        origin_uv_mm = centered_origin_uv_mm(rows, cols, pitch, pitch)
    origin = np.asarray(origin_uv_mm, dtype=np.float64)
    if origin.shape != (2,) or not np.all(np.isfinite(origin)):
        raise ValueError(f"{name}: origin_uv_mm must be 2 finite numbers, got {origin_uv_mm!r}")
    return np.ascontiguousarray(data, dtype="<f4"), pitch, origin


def read_stack_header(path: str | Path) -> PanelHeader:
    """The panel of a projection stack's header (origin, spacing, direction), without reading
    its pixels: what :func:`recon.rtk_xml.read_rtk_geometry` needs to place them.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ImageFileError: not an image, truncated, or unreadable.
        ValueError: not a scalar 3-D image, or a direction that mixes the panel's axes with
            the projection index (the file, the field and its value named).
    """
    path = _check_suffix(Path(path), PROJECTION_SUFFIXES, "projection stack")
    return _stack_header(_open_image(path), path)


def _stack_header(reader: sitk.ImageFileReader, path: Path) -> PanelHeader:
    direction = np.reshape(reader.GetDirection(), (3, 3))
    if np.abs(direction[2, :2]).max() > _DIRECTION_ATOL or np.abs(direction[:2, 2]).max() > (
        _DIRECTION_ATOL
    ):
        raise ValueError(
            f"{path}: Direction {np.round(direction, 6).tolist()} mixes the panel's axes with "
            "the projection index (third axis): a stack's projections must share one panel"
        )
    cols, rows, _ = reader.GetSize()
    spacing, origin = reader.GetSpacing(), reader.GetOrigin()
    return PanelHeader(
        rows,
        cols,
        (float(spacing[0]), float(spacing[1])),
        (float(origin[0]), float(origin[1])),
        tuple(tuple(float(x) for x in row[:2]) for row in direction[:2]),
        source=str(path),
    )


def read_projections(path: str | Path) -> ProjectionStack:
    """Read a projection stack written by :func:`write_projections` or by RTK (any origin,
    spacing and in-plane direction; see :func:`read_stack_header`).

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ImageFileError: not an image, truncated, or unreadable.
        ValueError: not a scalar 3-D image, or a direction that mixes the panel's axes with
            the projection index.
    """
    path = _check_suffix(Path(path), PROJECTION_SUFFIXES, "projection stack")
    reader = _open_image(path)
    header = _stack_header(reader, path)
    cols, rows, views = reader.GetSize()
    data = np.empty((views, rows, cols), dtype=np.float32)
    reader.SetOutputPixelType(sitk.sitkFloat32)
    # uncompressed stacks stream in slabs of views, so memory stays at one copy of the data;
    # compressed ones (smaller than their pixels) are read whole
    itemsize = sitk.GetArrayViewFromImage(sitk.Image([1, 1, 1], reader.GetPixelID())).itemsize
    uncompressed = path.stat().st_size >= cols * rows * views * itemsize
    chunk = _VIEWS_PER_READ if uncompressed else views
    for start in range(0, views, chunk):
        n = min(chunk, views - start)
        reader.SetExtractIndex((0, 0, start))
        reader.SetExtractSize((cols, rows, n))
        slab = _execute(reader, path)  # the view below borrows its buffer: keep it alive
        data[start : start + n] = sitk.GetArrayViewFromImage(slab)
    return ProjectionStack(data=data, header=header)


# -- shared file checks -----------------------------------------------------------------------


def _check_suffix(path: Path, allowed: tuple[str, ...], what: str) -> Path:
    if not path.name.lower().endswith(allowed):
        raise ValueError(f"{path}: unsupported {what} file type; use one of {', '.join(allowed)}")
    return path


def _check_parent(path: Path) -> None:
    if not path.parent.is_dir():
        raise FileNotFoundError(f"{path}: output folder {path.parent} does not exist")
    _check_no_nifti_twin(path)


def _check_no_nifti_twin(path: Path) -> None:
    """Refuse ``x.nii.gz`` beside ``x.nii``: ITK's NIfTI reader would silently read ``x.nii``."""
    if path.name.lower().endswith(".nii.gz"):
        twin = path.with_name(path.name[: -len(".gz")])
        if twin.exists():
            raise ValueError(
                f"{path}: {twin.name} exists beside it and ITK would read that file instead; "
                "remove or rename one of them"
            )


def _check_finite(data: np.ndarray, path: Path | str, what: str) -> None:
    bad = data.size - int(np.count_nonzero(np.isfinite(data)))
    if bad:
        raise ValueError(f"{path}: {what} contain {bad} non-finite values (NaN or inf)")


def _write_image(image: sitk.Image, path: Path) -> None:
    try:
        sitk.WriteImage(image, str(path))
    except RuntimeError as err:
        raise ImageFileError(f"{path}: could not write image: {_itk_reason(err)}") from err


def _open_image(path: Path) -> sitk.ImageFileReader:
    """A reader with the header read and checked: one scalar component, three dimensions."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    _check_no_nifti_twin(path)
    reader = sitk.ImageFileReader()
    reader.SetFileName(str(path))
    try:
        reader.ReadImageInformation()
    except RuntimeError as err:
        raise ImageFileError(f"{path}: not a readable image: {_itk_reason(err)}") from err
    if reader.GetDimension() != 3:
        raise ValueError(
            f"{path}: expected a 3-D image, got {reader.GetDimension()}-D of size "
            f"{reader.GetSize()}"
        )
    if reader.GetNumberOfComponents() != 1:
        raise ValueError(
            f"{path}: expected one value per voxel, got {reader.GetNumberOfComponents()}"
        )
    if path.name.lower().endswith((".nii", ".nii.gz")):
        _check_nifti_complete(path, reader)
    return reader


def _execute(reader: sitk.ImageFileReader, path: Path) -> sitk.Image:
    try:
        return reader.Execute()
    except RuntimeError as err:
        raise ImageFileError(
            f"{path}: could not read image data (truncated or corrupt file?): {_itk_reason(err)}"
        ) from err


def _check_nifti_complete(path: Path, reader: sitk.ImageFileReader) -> None:
    """Raise if a NIfTI file holds fewer bytes than its header promises.

    ITK's NIfTI reader silently returns partly zero images from truncated files.
    """
    needed = int(float(reader.GetMetaData("vox_offset"))) + _nifti_data_bytes(reader)
    if path.name.lower().endswith(".gz"):
        complete, holds = _gzip_holds(path, needed), "its gzip stream ends early"
    else:
        size = path.stat().st_size
        complete, holds = size >= needed, f"it holds {size}"
    if not complete:
        raise ImageFileError(
            f"{path}: truncated NIfTI file: the header promises {needed} bytes of header "
            f"and data, {holds}"
        )


def _nifti_data_bytes(reader: sitk.ImageFileReader) -> int:
    ndim = int(reader.GetMetaData("dim[0]"))
    count = math.prod(int(reader.GetMetaData(f"dim[{k}]")) for k in range(1, ndim + 1))
    return count * int(reader.GetMetaData("bitpix")) // 8


def _gzip_holds(path: Path, needed: int) -> bool:
    """Whether a gzip file decompresses completely to at least ``needed`` bytes.

    Fast path: a complete single-member file ends with its size modulo 2**32 (ISIZE).
    Otherwise the file is decompressed in chunks, counting bytes.
    """
    with path.open("rb") as handle:
        handle.seek(-4, 2)
        if int.from_bytes(handle.read(4), "little") == needed % (1 << 32):
            return True
    total = 0
    try:
        with gzip.open(path, "rb") as stream:
            while chunk := stream.read(_GZIP_CHUNK_BYTES):
                total += len(chunk)
    except (EOFError, OSError, zlib.error):
        return False
    return total >= needed


def _itk_reason(err: RuntimeError) -> str:
    """The first error line of a SimpleITK/ITK message, without source locations."""
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    for line in lines:
        for marker in ("sitk::ERROR:", "ITK ERROR:"):
            if marker in line:
                reason = line.split(marker, 1)[1]
                return _ITK_CLASS_PREFIX.sub("", reason).strip()
    return lines[-1] if lines else type(err).__name__

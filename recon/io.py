"""Volume and projection-stack files: NIfTI (.nii, .nii.gz) and MetaImage (.mha, .mhd).

This module is the file boundary of docs/conventions.md. In memory, volumes live in the world frame
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
wrong content (NaN or infinite pixels included) and for bad arguments. The pixel bytes a
header claims are checked against the bytes that hold them before anything is allocated
(:func:`check_claimed_bytes`), so a corrupt header claiming gigabytes is refused at once.
"""

from __future__ import annotations

import gzip
import math
import re
import struct
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from recon.rtk_xml import PanelHeader, centered_origin_uv_mm
from recon.volume import Unit, Volume, VolumeGrid

# ITK prints its warnings to stderr unasked, before our own message says what went wrong
# and what to do; what matters of them is in the errors raised here
sitk.ProcessObject.SetGlobalWarningDisplay(False)

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
OBLIQUE_GROWTH = 16
"""Most voxels an oblique volume's axis-aligned grid may hold, as a multiple of its own (a
tilt about one axis roughly doubles them; cubic voxels of the finest spacing multiply them by
the spacing's anisotropy)."""
_ORTHONORMAL_ATOL = 1e-4
"""Largest |D^T D - I| entry of an image direction taken as a rotation (DICOM's orientation
cosines carry about six digits)."""
_DIRECTION_ATOL = 1e-4
_VIEWS_PER_READ = 32
_GZIP_CHUNK_BYTES = 1 << 22
_ITK_CLASS_PREFIX = re.compile(r"^\s*\w+\(0x[0-9a-fA-F]+\):\s*")
_META_HEADER_MAX_BYTES = 1 << 16
_META_LOCAL = ("LOCAL", "Local", "local")  # what MetaIO takes for data after the header
_META_FIELD = re.compile(r"^\s*([^=:]+?)\s*[=:](.*)$")

MAX_DEFLATE_RATIO = 1032
"""Deflate (zlib, gzip) expands its input at most this many times: a compressed file claiming
more pixel bytes than this times its size is corrupt."""


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
        ValueError: not a scalar 3-D image, a direction that is not a rotation, an oblique
            volume whose axis-aligned grid would be too large, a spacing or origin that is not
            finite and positive, a missing or conflicting unit, NaN or infinite values, or a
            label file with non-integer pixels.
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
    # before reading: ITK's reader hangs on some directions that are not rotations
    _check_rotation(np.reshape(reader.GetDirection(), (3, 3)), path)
    data, grid = identity_oriented(_execute(reader, path), path, label=resolved == "label")
    if resolved != "label":
        data = data.astype(np.float32, copy=False)
        _check_finite(data, path, "volume data")
    return Volume(data=data, grid=grid, unit=resolved)


def check_image_file(path: str | Path) -> None:
    """Raise unless ``path`` is a readable 3-D scalar image holding the pixels its header
    claims; its pixels are not read.

    Args:
        path: The image file (any format SimpleITK reads).

    Raises:
        FileNotFoundError: ``path`` is not a file.
        ImageFileError: not an image, truncated, or unreadable.
        ValueError: not 3-D, or more than one value per voxel.
    """
    _open_image(Path(path))


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
        image = _axis_aligned(image, label, path)
    signed_perm = _signed_permutation(np.reshape(image.GetDirection(), (3, 3)), path)
    data, spacing, origin = _reorient_to_identity(
        sitk.GetArrayFromImage(image), image.GetSpacing(), image.GetOrigin(), signed_perm
    )
    try:
        return data, VolumeGrid(data.shape, spacing, origin)
    except ValueError as err:
        raise ValueError(f"{path}: {err}") from None


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
    with np.errstate(over="ignore", invalid="ignore"):
        error = float(np.abs(direction.T @ direction - np.eye(3)).max())
    if not error <= _ORTHONORMAL_ATOL:
        raise ValueError(
            f"{path}: image direction {np.round(direction, 6).tolist()} (columns are the "
            f"file's axes in LPS) is not a rotation (|D^T D - I| = {error:.2g}, tolerance "
            f"{_ORTHONORMAL_ATOL:g})"
        )


def _axis_aligned(image: sitk.Image, label: bool, path: Path) -> sitk.Image:
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
    extent = (high - low) / spacing
    voxels = float(np.prod(np.floor(extent) + 1)) if np.isfinite(extent).all() else np.inf
    limit = OBLIQUE_GROWTH * float(np.prod(size))
    if not voxels <= limit:
        raise ValueError(
            f"{path}: the oblique volume on an axis-aligned grid of {spacing:g} mm voxels would "
            f"hold {voxels:.3g} voxels, more than {OBLIQUE_GROWTH} x its own {np.prod(size)}: "
            "resample it with isotropic voxels first"
        )
    shape = np.floor(extent + 1e-6).astype(int) + 1
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

    Args:
        path: Projection stack (.mha or .mhd).

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

    Args:
        path: Projection stack (.mha or .mhd), line integrals.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ImageFileError: not an image, truncated, or unreadable.
        ValueError: not a scalar 3-D image, a direction that mixes the panel's axes with
            the projection index, or NaN or infinite values.
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
    _check_finite(data, path, "projections")
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
    """A reader with the header read and checked: one scalar component, three dimensions, and
    the pixels it claims held by the file (:func:`check_claimed_bytes`)."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    _check_no_nifti_twin(path)
    if path.name.lower().endswith((".mha", ".mhd")):
        _metaimage_header(path)  # before ITK, which crashes on some corrupt headers
    elif path.name.lower().endswith((".nii", ".nii.gz")):
        _nifti_header(path)  # before ITK, which hangs on some
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
    check_claimed_bytes(path, reader)
    return reader


def check_claimed_bytes(path: Path, reader: sitk.ImageFileReader) -> None:
    """ImageFileError unless the pixels the header of ``path`` (read by ``reader``) claims fit in
    the bytes that hold them: all of them for uncompressed data, a :data:`MAX_DEFLATE_RATIO`-th
    for compressed data. Reads headers and file sizes only, so a corrupt header claiming
    gigabytes is refused before ITK allocates them."""
    name = path.name.lower()
    if name.endswith((".nii", ".nii.gz")):
        _check_nifti_complete(path, reader)
    elif name.endswith((".mha", ".mhd")):
        _check_metaimage_complete(path, reader)


def _claimed_bytes(reader: sitk.ImageFileReader) -> int:
    """Bytes of the pixels ``reader``'s header claims, as ITK would allocate them."""
    one = sitk.Image([1] * reader.GetDimension(), reader.GetPixelID())
    itemsize = sitk.GetArrayViewFromImage(one).itemsize
    return math.prod(reader.GetSize()) * reader.GetNumberOfComponents() * itemsize


def _metaimage_header(path: Path) -> tuple[dict[str, str], int]:
    """A MetaImage header's fields (as MetaIO reads them: ``key = value`` or ``key : value``
    lines up to ``ElementDataFile``, looked for in the first ``_META_HEADER_MAX_BYTES``) and
    its length in bytes.

    Raises ImageFileError for a field given twice or an ``ElementDataFile`` that is neither
    ``LOCAL`` nor a file (file lists and patterns are not read), ValueError for ``NDims`` other
    than 1 to 3: MetaIO corrupts its memory or crashes the process on some of those, and our
    images have three dimensions. A header without ``NDims`` or ``ElementDataFile`` is left for
    ITK to refuse.
    """
    with path.open("rb") as handle:
        head = handle.read(_META_HEADER_MAX_BYTES)
    fields, header_bytes = {}, 0
    for line in head.split(b"\n"):
        header_bytes += len(line) + 1
        match = _META_FIELD.match(line.decode("latin-1"))
        if match is None:
            continue
        key, value = match.groups()
        if key in fields:
            raise ImageFileError(f"{path}: corrupt MetaImage header: {key} is given twice")
        fields[key] = value.strip()
        if key == "ElementDataFile":
            break
    ndims = fields.get("NDims", "3").split()
    if not ndims or ndims[0] not in ("1", "2", "3"):
        raise ValueError(
            f"{path}: expected a 3-D image, got NDims = {fields['NDims']!r} in its header"
        )
    data_file = fields.get("ElementDataFile", "LOCAL")
    if data_file not in _META_LOCAL and not (path.parent / data_file).is_file():
        raise ImageFileError(
            f"{path}: its ElementDataFile {data_file!r} is not a file beside it (file lists "
            "and patterns are not read)"
        )
    return fields, header_bytes


def _check_metaimage_complete(path: Path, reader: sitk.ImageFileReader) -> None:
    """The MetaImage check of :func:`check_claimed_bytes`."""
    fields, header_bytes = _metaimage_header(path)
    data_file = fields.get("ElementDataFile")
    if data_file is None:  # ITK read it: a header longer than we look
        return
    if data_file in _META_LOCAL:
        stored = path.stat().st_size - header_bytes
    else:
        stored = (path.parent / data_file).stat().st_size
    claimed = _claimed_bytes(reader)
    if fields.get("CompressedData", "").lower() == "true":
        limit, holds = stored * MAX_DEFLATE_RATIO, f"{stored} compressed bytes"
    elif fields.get("BinaryData", "").lower() == "false":  # text: at least a byte per value
        claimed, limit, holds = math.prod(reader.GetSize()), stored, f"{stored} bytes of text"
    else:
        limit, holds = stored, f"{stored} bytes"
    if claimed > limit:
        raise ImageFileError(
            f"{path}: truncated or corrupt MetaImage: its header claims {claimed} bytes of "
            f"pixels ({reader.GetSize()}), the file holds {holds}"
        )


def _execute(reader: sitk.ImageFileReader, path: Path) -> sitk.Image:
    try:
        return reader.Execute()
    except RuntimeError as err:
        raise ImageFileError(
            f"{path}: could not read image data (truncated or corrupt file?): {_itk_reason(err)}"
        ) from err


@dataclass(frozen=True)
class _NiftiLayout:
    """Where NIfTI-1 (348-byte header) or NIfTI-2 (540) keeps the fields checked here: byte
    offsets and struct codes of one integer and one real number."""

    int_code: str
    real_code: str
    dim: int
    bitpix: int
    pixdim: int
    vox_offset: int
    vox_offset_code: str
    scl_slope: int
    quatern: int
    srow: int


_NIFTI_LAYOUTS = {
    348: _NiftiLayout("h", "f", 40, 72, 76, 108, "f", 112, 256, 280),
    540: _NiftiLayout("q", "d", 16, 14, 104, 168, "q", 176, 352, 400),
}


@dataclass(frozen=True)
class _NiftiHeader:
    dim: tuple[int, ...]
    bitpix: int
    vox_offset: int


def _nifti_header(path: Path) -> _NiftiHeader | None:
    """The fields of a NIfTI-1 or -2 header (plain or gzipped) that size and place the image,
    checked before ITK reads it: ITK hangs on some non-finite orientations and silently takes
    1 mm for a voxel size that is not a finite number > 0.

    Returns None for what is no NIfTI header at all (unreadable, another size), which ITK
    refuses. Raises ImageFileError naming the file and the field: dim[0] not 1..7, a size < 1,
    a voxel size not finite and > 0, a non-finite vox_offset, scaling, quaternion, offset or
    sform row.
    """
    try:
        with gzip.open(path) if path.name.lower().endswith(".gz") else path.open("rb") as fh:
            head = fh.read(540)
    except (EOFError, OSError, zlib.error):
        return None
    order = next((o for o in "<>" if len(head) >= 4 and _hdr_size(head, o) in _NIFTI_LAYOUTS), "")
    if not order or len(head) < _hdr_size(head, order):
        return None
    at = _NIFTI_LAYOUTS[_hdr_size(head, order)]

    def values(offset: int, count: int, code: str) -> tuple:
        return struct.unpack_from(f"{order}{count}{code}", head, offset)

    dim = values(at.dim, 8, at.int_code)
    if not 1 <= dim[0] <= 7 or min(dim[1 : dim[0] + 1]) < 1:
        raise ImageFileError(f"{path}: corrupt NIfTI header: dim = {list(dim)}")
    pixdim = values(at.pixdim, 8, at.real_code)
    for k in range(1, min(dim[0], 3) + 1):
        if not (math.isfinite(pixdim[k]) and pixdim[k] > 0):
            raise ImageFileError(
                f"{path}: corrupt NIfTI header: pixdim[{k}] = {pixdim[k]!r}, the voxel size "
                "must be finite and > 0 mm"
            )
    (vox_offset,) = values(at.vox_offset, 1, at.vox_offset_code)
    reals = {
        "vox_offset": (vox_offset,),
        "scl_slope, scl_inter": values(at.scl_slope, 2, at.real_code),
        "quatern_b..d, qoffset_x..z": values(at.quatern, 6, at.real_code),
        "srow_x, srow_y, srow_z": values(at.srow, 12, at.real_code),
    }
    for name, numbers in reals.items():
        if not all(math.isfinite(x) for x in numbers):
            raise ImageFileError(f"{path}: corrupt NIfTI header: {name} = {list(numbers)}")
    if vox_offset < 0:
        raise ImageFileError(f"{path}: corrupt NIfTI header: vox_offset = {vox_offset}")
    (bitpix,) = values(at.bitpix, 1, "h")
    return _NiftiHeader(dim[1 : dim[0] + 1], bitpix, int(vox_offset))


def _hdr_size(head: bytes, order: str) -> int:
    """A NIfTI header's first field, sizeof_hdr, read in byte order ``order`` ("<" or ">")."""
    return struct.unpack_from(f"{order}i", head)[0]


def _check_nifti_complete(path: Path, reader: sitk.ImageFileReader) -> None:
    """Raise if a NIfTI file holds fewer bytes than its header promises.

    ITK's NIfTI reader silently returns partly zero images from truncated files.
    """
    header = _nifti_header(path)
    if header is None:
        raise ImageFileError(f"{path}: ITK read a header that is not NIfTI-1 or NIfTI-2")
    data_bytes = math.prod(header.dim) * max(header.bitpix, 0) // 8
    needed = header.vox_offset + max(data_bytes, _claimed_bytes(reader))
    size = path.stat().st_size
    if path.name.lower().endswith(".gz"):
        complete = size * MAX_DEFLATE_RATIO >= needed and _gzip_holds(path, needed)
        holds = "its gzip stream ends early"
    else:
        complete, holds = size >= needed, f"it holds {size}"
    if not complete:
        raise ImageFileError(
            f"{path}: truncated NIfTI file: the header promises {needed} bytes of header "
            f"and data, {holds}"
        )


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
                reason = _ITK_CLASS_PREFIX.sub("", line.split(marker, 1)[1]).strip()
                if reason.startswith("Unable to determine ImageIO reader"):
                    return "no image reader recognises its content"
                return reason
    return lines[-1] if lines else type(err).__name__

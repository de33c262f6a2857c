"""DICOM CT series: export one file per axial slice, and import a scanner's series, with
SimpleITK (GDCM).

Values are stored as int16 with RescaleSlope/RescaleIntercept in Hounsfield units,
``HU = 1000 * (mu - mu_water) / mu_water`` for attenuation volumes (1/mm). The slope is 1 HU
whenever the volume's HU range spans at most 65532 HU (quantisation error <= 0.5 HU);
wider ranges double it until they fit (error <= slope / 2). Positions are LPS mm, which is
DICOM's patient frame, so no conversion happens here.

Import (:func:`read_dicom_series`): one CT series from a folder, slices ordered by position
along their normal (GDCM), the modality rescale applied (values in HU), axes that are a
signed permutation of LPS reoriented like recon.io's volumes and tilted ones resampled onto an
axis-aligned grid (recon.io.identity_oriented), unequal slice
gaps and other modalities refused with the folder and the tag named.
"""

from __future__ import annotations

import math
import mmap
import struct
import time
import uuid
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from recon.attenuation import mu_to_hu
from recon.io import MAX_DEFLATE_RATIO, ImageFileError, identity_oriented
from recon.volume import Volume

CT_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.2"
"""SOP Class UID of CT Image Storage."""

UNCOMPRESSED_SYNTAXES = frozenset(
    {"1.2.840.10008.1.2", "1.2.840.10008.1.2.1", "1.2.840.10008.1.2.2"}
)
"""Transfer Syntax UIDs (0002,0010) whose pixel data are stored as they are (implicit and
explicit VR little endian, explicit VR big endian)."""

_INT16_SPAN = 65532  # stored values stay within -32767..32767 around a whole-HU intercept
_LO_MAX_CHARS = 64  # DICOM "Long String"
_DS_MAX_CHARS = 16  # DICOM "Decimal String"


def write_dicom_series(
    folder: str | Path,
    volume: Volume,
    mu_water_per_mm: float,
    series_description: str = "dualarm-cbct reconstruction",
    patient_id: str = "ANONYMOUS",
) -> list[Path]:
    """Write a volume as a DICOM CT Image Storage series, one file per z-slice.

    Args:
        folder: output folder; created if missing, refused if not empty.
        volume: values in 1/mm (converted to HU) or HU (written as is) on an LPS grid.
        mu_water_per_mm: linear attenuation of water at the scan's effective energy, 1/mm.
        series_description: SeriesDescription (0008,103E), at most 64 characters.
        patient_id: PatientID (0010,0020), at most 64 characters.

    Returns:
        The files written, in slice order (increasing z, InstanceNumber 1, 2, ...).

    Raises:
        FileExistsError: ``folder`` exists and is not empty.
        NotADirectoryError: ``folder`` is a file.
        ValueError: a label volume, non-finite values, a bad mu_water or text field.
        OSError: SimpleITK could not write a slice.
    """
    folder = Path(folder)
    _check_folder(folder)
    _check_text("series_description", series_description, folder)
    _check_text("patient_id", patient_id, folder)
    hu = _to_hu(volume, mu_water_per_mm, folder)
    slope, intercept = rescale_for(float(hu.min()), float(hu.max()))
    folder.mkdir(parents=True, exist_ok=True)
    series_tags = _series_tags(volume, slope, intercept, series_description, patient_id)
    nz = volume.grid.shape[0]
    width = max(4, len(str(nz)))
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    paths = []
    for k in range(nz):
        path = folder / f"slice_{k + 1:0{width}d}.dcm"
        # A one-slice 3-D image, not a 2-D one: GDCM then takes SpacingBetweenSlices from
        # the z spacing; from 2-D images it writes 1 mm once the process has read a DICOM file.
        image = sitk.GetImageFromArray(hu[k : k + 1])
        image.SetSpacing(volume.grid.spacing_mm)
        image.SetOrigin(tuple(volume.grid.index_to_world((0, 0, k))))
        for tag, value in {**series_tags, **_slice_tags(volume, k)}.items():
            image.SetMetaData(tag, value)
        writer.SetFileName(str(path))
        try:
            writer.Execute(image)
        except RuntimeError as err:
            raise OSError(f"{path}: could not write DICOM slice: {err}") from err
        paths.append(path)
    return paths


def rescale_for(hu_min: float, hu_max: float) -> tuple[float, float]:
    """RescaleSlope and RescaleIntercept storing [hu_min, hu_max] HU in int16.

    Returns:
        (slope, intercept): slope 1 HU, or the smallest power of two fitting the range;
        intercept 0 when the range fits around zero, else the range's middle (whole HU).
    """
    slope = 1.0
    while (hu_max - hu_min) / slope > _INT16_SPAN:
        slope *= 2.0
    limit = 0.5 * _INT16_SPAN * slope
    if -limit <= hu_min and hu_max <= limit:
        return slope, 0.0
    return slope, float(round(0.5 * (hu_min + hu_max)))


def _check_folder(folder: Path) -> None:
    if folder.exists() and not folder.is_dir():
        raise NotADirectoryError(f"{folder}: exists and is not a folder")
    if folder.is_dir() and any(folder.iterdir()):
        raise FileExistsError(f"{folder}: folder is not empty; DICOM series need their own folder")


def _check_text(name: str, value: str, folder: Path) -> None:
    if len(value) > _LO_MAX_CHARS or "\\" in value or not value.isprintable():
        raise ValueError(
            f"{folder}: {name} must be at most {_LO_MAX_CHARS} printable characters "
            f"without '\\', got {value!r}"
        )


def _to_hu(volume: Volume, mu_water_per_mm: float, folder: Path) -> np.ndarray:
    """The volume in HU, float64, indexed [z, y, x]."""
    if volume.unit == "label":
        raise ValueError(f"{folder}: label volumes cannot be written as a CT series")
    mu_water = float(mu_water_per_mm)
    if not (math.isfinite(mu_water) and mu_water > 0):
        raise ValueError(f"{folder}: mu_water_per_mm must be finite and > 0, got {mu_water!r}")
    data = np.asarray(volume.data, dtype=np.float64)
    bad = data.size - int(np.count_nonzero(np.isfinite(data)))
    if bad:
        raise ValueError(f"{folder}: volume data contain {bad} non-finite values (NaN or inf)")
    if volume.unit == "HU":
        return data
    return mu_to_hu(data, mu_water)


def _series_tags(
    volume: Volume, slope: float, intercept: float, description: str, patient_id: str
) -> dict[str, str]:
    """Tags shared by every slice of the series (SimpleITK keys "gggg|eeee")."""
    sx, sy, sz = volume.grid.spacing_mm
    date, clock = time.strftime("%Y%m%d"), time.strftime("%H%M%S")
    return {
        "0008|0008": "DERIVED\\SECONDARY\\AXIAL",  # ImageType
        "0008|0016": CT_IMAGE_STORAGE,  # SOPClassUID
        "0008|0020": date,  # StudyDate
        "0008|0021": date,  # SeriesDate
        "0008|0030": clock,  # StudyTime
        "0008|0031": clock,  # SeriesTime
        "0008|0060": "CT",  # Modality
        "0008|0070": "dualarm-cbct",  # Manufacturer
        "0008|103e": description,  # SeriesDescription
        "0010|0020": patient_id,  # PatientID
        "0018|0050": _ds(sz),  # SliceThickness
        "0018|0088": _ds(sz),  # SpacingBetweenSlices
        "0020|000d": _new_uid(),  # StudyInstanceUID
        "0020|000e": _new_uid(),  # SeriesInstanceUID
        "0020|0010": "1",  # StudyID
        "0020|0011": "1",  # SeriesNumber
        "0020|0037": "1\\0\\0\\0\\1\\0",  # ImageOrientationPatient
        "0020|0052": _new_uid(),  # FrameOfReferenceUID
        "0028|0030": f"{_ds(sy)}\\{_ds(sx)}",  # PixelSpacing: row spacing \ column spacing
        "0028|0100": "16",  # BitsAllocated
        "0028|0101": "16",  # BitsStored
        "0028|0102": "15",  # HighBit
        "0028|0103": "1",  # PixelRepresentation: signed
        "0028|1052": _ds(intercept),  # RescaleIntercept
        "0028|1053": _ds(slope),  # RescaleSlope
        "0028|1054": "HU",  # RescaleType
    }


def _slice_tags(volume: Volume, k: int) -> dict[str, str]:
    """Tags of slice ``k``: position of its first voxel, LPS mm, and its identity."""
    x, y, z = volume.grid.index_to_world((0, 0, k))
    return {
        "0008|0018": _new_uid(),  # SOPInstanceUID
        "0020|0013": str(k + 1),  # InstanceNumber
        "0020|0032": f"{_ds(x)}\\{_ds(y)}\\{_ds(z)}",  # ImagePositionPatient
        "0020|1041": _ds(z),  # SliceLocation
    }


def _new_uid() -> str:
    """A DICOM UID derived from a random UUID (root 2.25, PS3.5 B.2)."""
    return f"2.25.{uuid.uuid4().int}"


def _ds(value: float) -> str:
    """A number as a DICOM Decimal String: at most 16 characters, as precise as fits."""
    for digits in range(12, 0, -1):
        text = f"{value:.{digits}g}"
        if len(text) <= _DS_MAX_CHARS:
            return text
    raise ValueError(f"cannot write {value!r} as a DICOM decimal string")


def read_dicom_series(folder: str | Path) -> Volume:
    """The CT series in ``folder`` as a volume in HU on an identity-direction grid.

    Raises:
        FileNotFoundError: ``folder`` does not exist.
        ImageFileError: no DICOM series in it, a slice GDCM cannot read, or one whose header
            claims more pixel bytes than it holds.
        ValueError: several series, a modality other than CT (0008,0060), slices whose gaps
            differ by more than 1 % of the spacing or whose positions are not numbers, an
            orientation that is not a rotation, NaN or infinite values.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: no such folder (a DICOM CT series is a folder)")
    files = series_files(folder)
    for name in files:
        open_dicom(name)
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(files)
    reader.MetaDataDictionaryArrayUpdateOn()
    try:
        image = reader.Execute()
    except RuntimeError as err:
        raise ImageFileError(f"{folder}: could not read the series ({err})") from None
    modality = (
        reader.GetMetaData(0, "0008|0060").strip()
        if reader.HasMetaDataKey(0, "0008|0060")
        else None
    )
    if modality != "CT":
        raise ValueError(
            f"{folder}: Modality (0008,0060) is {modality!r}; a static scan in CT numbers "
            "must be a CT series"
        )
    _check_slice_gaps(reader, len(files), image, folder)
    data, grid = identity_oriented(image, folder)
    data = data.astype(np.float32)
    bad = data.size - int(np.count_nonzero(np.isfinite(data)))
    if bad:
        raise ValueError(f"{folder}: {bad} voxels are NaN or infinite after the rescale")
    return Volume(data, grid, "HU")


def _check_slice_gaps(reader, count: int, image: sitk.Image, folder: Path) -> None:
    """ValueError unless consecutive slices lie one spacing apart along their normal (1 %)."""
    if count < 2:
        return
    direction = np.reshape(image.GetDirection(), (3, 3))
    positions = np.array([_position(reader, k, folder) for k in range(count)])
    along = positions @ direction[:, 2]
    gaps = np.diff(along)
    spacing = image.GetSpacing()[2]
    worst = int(np.argmax(np.abs(gaps - spacing)))
    if abs(gaps[worst] - spacing) > 0.01 * spacing:
        raise ValueError(
            f"{folder}: slices {worst + 1} and {worst + 2} lie {gaps[worst]:.3f} mm apart along "
            f"Image Position Patient (0020,0032), the series' spacing is {spacing:.3f} mm: "
            "unequal slice gaps (a missing slice?)"
        )


def _position(reader: sitk.ImageSeriesReader, k: int, folder: Path) -> list[float]:
    """Image Position Patient (0020,0032) of slice ``k``, LPS mm; ValueError naming the
    folder and the slice unless it is three finite numbers."""
    text = reader.GetMetaData(k, "0020|0032") if reader.HasMetaDataKey(k, "0020|0032") else ""
    try:
        position = [float(x) for x in text.split("\\")]
    except ValueError:
        position = []
    if len(position) != 3 or not all(math.isfinite(x) for x in position):
        raise ValueError(
            f"{folder}: slice {k + 1}: Image Position Patient (0020,0032) is {text!r}, "
            "not three finite numbers (mm)"
        )
    return position


def series_files(folder: Path) -> list[str]:
    """The files of the one DICOM series in ``folder``, in slice order (GDCM); ImageFileError
    when GDCM finds none or cannot scan a file or a file is not sound DICOM
    (:func:`check_dicom_lengths`: GDCM scans every file of the folder), ValueError for several
    series."""
    for path in sorted(folder.iterdir()):
        if path.is_file():
            check_dicom_lengths(path)
    try:
        ids = sitk.ImageSeriesReader.GetGDCMSeriesIDs(str(folder))
        if len(ids) == 1:
            return list(sitk.ImageSeriesReader.GetGDCMSeriesFileNames(str(folder), ids[0]))
    except RuntimeError as err:
        raise ImageFileError(f"{folder}: a file GDCM cannot scan ({_first_line(err)})") from None
    if not ids:
        raise ImageFileError(f"{folder}: no DICOM series in this folder")
    raise ValueError(f"{folder}: {len(ids)} DICOM series in one folder; give one")


def open_dicom(path: str | Path) -> sitk.ImageFileReader:
    """A reader of one DICOM file with its header read, its elements checked to end within it
    (:func:`check_dicom_lengths`) and the pixel bytes it claims checked against its size
    (:func:`check_dicom_claim`); ImageFileError naming ``path`` otherwise."""
    check_dicom_lengths(Path(path))
    reader = sitk.ImageFileReader()
    reader.SetFileName(str(path))
    reader.SetImageIO("GDCMImageIO")
    try:
        reader.ReadImageInformation()
    except RuntimeError as err:
        raise ImageFileError(f"{path}: not a readable DICOM image ({_first_line(err)})") from None
    check_dicom_claim(Path(path), reader)
    return reader


def check_dicom_claim(path: Path, reader: sitk.ImageFileReader) -> None:
    """ImageFileError unless the pixel bytes the header of DICOM file ``path`` claims (Rows x
    Columns x frames x samples x Bits Allocated) fit in the file: all of them for uncompressed
    transfer syntaxes, a ``MAX_DEFLATE_RATIO``-th for compressed ones. Checked before any pixel
    is read, so a corrupt header claiming gigabytes is refused at once."""
    bits = _int_tag(reader, "0028|0100", 16)
    samples = _int_tag(reader, "0028|0002", 1)
    claimed = math.prod(reader.GetSize()) * samples * max(bits, 1) // 8
    stored = path.stat().st_size
    syntax = transfer_syntax(path)
    limit = stored if syntax in UNCOMPRESSED_SYNTAXES else stored * MAX_DEFLATE_RATIO
    if claimed > limit:
        raise ImageFileError(
            f"{path}: truncated or corrupt DICOM file: its header claims {claimed} bytes of "
            f"pixels ({reader.GetSize()} x {samples} x {bits} bits, transfer syntax {syntax}), "
            f"the file holds {stored}"
        )


def transfer_syntax(path: Path) -> str:
    """The Transfer Syntax UID (0002,0010) of a DICOM file's meta header; implicit VR little
    endian (DICOM's default) when there is none."""
    with path.open("rb") as handle:
        head = handle.read(4096)
    at = head.find(b"\x02\x00\x10\x00UI")
    if at < 0 or at + 8 > len(head):
        return "1.2.840.10008.1.2"
    length = int.from_bytes(head[at + 6 : at + 8], "little")
    return head[at + 8 : at + 8 + length].rstrip(b"\0 ").decode("ascii", "replace")


def _int_tag(reader: sitk.ImageFileReader, key: str, default: int) -> int:
    try:
        return int(reader.GetMetaData(key).strip())
    except (RuntimeError, ValueError):
        return default


def _first_line(err: Exception) -> str:
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    return lines[-1] if lines else type(err).__name__


_VRS = frozenset(
    b"AE AS AT CS DA DS DT FL FD IS LO LT OB OD OF OL OV OW PN SH SL SQ SS ST SV TM UC UI UL "
    b"UN UR US UT UV".split()
)
_LONG_VRS = frozenset(b"OB OD OF OL OV OW SQ UC UN UR UT UV".split())
_UNDEFINED = 0xFFFFFFFF
_ITEM, _ITEM_END, _SEQUENCE_END = 0xE000, 0xE00D, 0xE0DD
_PIXEL_DATA = (0x7FE0, 0x0010)
_MAX_NESTING = 16


class _Corrupt(Exception):
    """Raised inside :func:`check_dicom_lengths`' walk; becomes ImageFileError."""


def has_dicom_preamble(head: bytes) -> bool:
    """Whether a file's first 132 bytes are a DICOM Part 10 preamble ("DICM" at byte 128).

    Args:
        head: The file's first 132 bytes (or fewer, for a shorter file).
    """
    return head[128:132] == b"DICM"


def check_dicom_lengths(path: Path) -> None:
    """ImageFileError unless ``path`` is a DICOM Part 10 file ("DICM" at byte 128) whose
    elements, items and sequences all end within the file and carry valid VRs.

    GDCM allocates what a length field says before reading, so one corrupt length (e.g. an
    invalid VR read as a 4-byte length) costs gigabytes; this walk reads lengths only (the file
    is memory-mapped, nothing is allocated). A deflated data set is checked up to its meta
    header.
    """
    try:
        with (
            path.open("rb") as handle,
            mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ) as buf,
        ):
            if not has_dicom_preamble(buf[:132]):
                raise _Corrupt("not a DICOM file (no 'DICM' at byte 128)")
            pos = _walk(buf, 132, len(buf), "<", True, 0, meta=True)
            syntax = transfer_syntax(path)
            if syntax != "1.2.840.10008.1.2.1.99":  # deflated: nothing more to walk
                order = ">" if syntax == "1.2.840.10008.1.2.2" else "<"
                _walk(buf, pos, len(buf), order, syntax != "1.2.840.10008.1.2", 0)
    except ValueError as err:  # mmap of an empty file
        raise ImageFileError(f"{path}: not a DICOM file ({err})") from None
    except _Corrupt as err:
        raise ImageFileError(f"{path}: corrupt DICOM file: {err}") from None


def _walk(buf, pos: int, end: int, order: str, explicit: bool, depth: int, meta=False) -> int:
    """Walk the elements from ``pos`` to ``end`` (or a delimiter); the position after them.
    With ``meta``, only the meta header's group 0002 (explicit VR little endian)."""
    if depth > _MAX_NESTING:
        raise _Corrupt(f"sequences nested deeper than {_MAX_NESTING} at byte {pos}")
    while pos < end:
        if pos + 8 > end:
            raise _Corrupt(f"an element header is cut off at byte {pos}")
        group, element = struct.unpack_from(f"{order}HH", buf, pos)
        if meta and group != 0x0002:
            return pos
        if group == 0xFFFE:
            (length,) = struct.unpack_from(f"{order}I", buf, pos + 4)
            if depth == 0 or element not in (_ITEM, _ITEM_END, _SEQUENCE_END):
                raise _Corrupt(f"item or delimiter (FFFE,{element:04X}) misplaced at byte {pos}")
            pos += 8
            if element != _ITEM:
                return pos
            pos = _value(buf, pos, end, length, order, explicit, depth, items=True)
            continue
        vr = b""
        if explicit:
            vr = bytes(buf[pos + 4 : pos + 6])
            if vr not in _VRS:
                raise _Corrupt(f"element ({group:04X},{element:04X}) at byte {pos}: VR {vr!r}")
        if not explicit or vr in _LONG_VRS:
            header = 12 if explicit else 8
            if pos + header > end:
                raise _Corrupt(f"an element header is cut off at byte {pos}")
            (length,) = struct.unpack_from(f"{order}I", buf, pos + header - 4)
        else:
            header, (length,) = 8, struct.unpack_from(f"{order}H", buf, pos + 6)
        pixels = (group, element) == _PIXEL_DATA
        # an undefined length outside the pixel data: a sequence (UN ones in implicit VR)
        nested = vr == b"SQ" or (length == _UNDEFINED and not pixels)
        pos = _value(
            buf,
            pos + header,
            end,
            length,
            order,
            explicit and vr != b"UN",
            depth,
            items=nested,
            fragments=pixels,
        )
    return pos


def _value(buf, pos, end, length, order, explicit, depth, items=False, fragments=False) -> int:
    """Skip one value of ``length`` bytes at ``pos`` (walking its items when it holds a data
    set, an item or a sequence); the position after it."""
    if length == _UNDEFINED:
        if fragments:
            return _fragments(buf, pos, end, order)
        if not items:
            raise _Corrupt(f"a value at byte {pos} has an undefined length but holds no items")
        return _walk(buf, pos, end, order, explicit, depth + 1)
    if pos + length > end:
        raise _Corrupt(f"a value of {length} bytes at byte {pos} runs past the file's {end}")
    if items:
        _walk(buf, pos, pos + length, order, explicit, depth + 1)
    return pos + length


def _fragments(buf, pos: int, end: int, order: str) -> int:
    """Skip encapsulated pixel data's items up to its sequence delimiter."""
    while pos + 8 <= end:
        group, element, length = struct.unpack_from(f"{order}HHI", buf, pos)
        pos += 8
        if (group, element) == (0xFFFE, _SEQUENCE_END):
            return pos
        if (group, element) != (0xFFFE, _ITEM) or pos + length > end:
            raise _Corrupt(f"a pixel data fragment at byte {pos - 8} is corrupt")
        pos += length
    raise _Corrupt("encapsulated pixel data without an end")

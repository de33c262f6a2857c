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
import time
import uuid
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from recon.attenuation import mu_to_hu
from recon.io import ImageFileError, identity_oriented
from recon.volume import Volume

CT_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.2"
"""SOP Class UID of CT Image Storage."""

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
        ImageFileError: no DICOM series in it, or a slice GDCM cannot read.
        ValueError: several series, a modality other than CT (0008,0060), slices whose gaps
            differ by more than 1 % of the spacing, an orientation that is not a rotation.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: no such folder (a DICOM CT series is a folder)")
    ids = sitk.ImageSeriesReader.GetGDCMSeriesIDs(str(folder))
    if not ids:
        raise ImageFileError(f"{folder}: no DICOM series in this folder")
    if len(ids) > 1:
        raise ValueError(f"{folder}: {len(ids)} DICOM series in one folder; give one")
    files = sitk.ImageSeriesReader.GetGDCMSeriesFileNames(str(folder), ids[0])
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
    return Volume(data.astype(np.float32), grid, "HU")


def _check_slice_gaps(reader, count: int, image: sitk.Image, folder: Path) -> None:
    """ValueError unless consecutive slices lie one spacing apart along their normal (1 %)."""
    if count < 2:
        return
    direction = np.reshape(image.GetDirection(), (3, 3))
    positions = np.array(
        [[float(x) for x in reader.GetMetaData(k, "0020|0032").split("\\")] for k in range(count)]
    )
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

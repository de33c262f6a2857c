"""Fluoroscopy frames from files: RTK-style .mha stacks, clinical DICOM, or TIFF/PNG images.

.mha/.mhd stacks (recon.io) hold line integrals already. DICOM comes as single CR/DX images, a
folder of them (one series, ordered by instance number), or a multi-frame XA/RF file. This is
the one place where DICOM pixels become registration frames:

- values are taken after the modality rescale (SimpleITK applies RescaleSlope/Intercept);
- where the X-ray image says how its values relate to the beam (Pixel Intensity Relationship
  (0028,1040) LIN or LOG, and its Sign (0028,1041), +1 when lower values mean less beam
  intensity: required in DX, XA and RF images), that decides: LIN +1 values are intensities,
  so the line integral is ``-ln(value)`` up to an offset; LOG +1 values are its negative
  (``-value``); Sign -1 values grow with attenuation as they are. Fluoroscopy (XA/RF) commonly
  stores intensity, bone dark: reading it by its display would invert every frame;
- otherwise (DISP, or no tags) the displayed brightness stands in: MONOCHROME2 as stored,
  MONOCHROME1 inverted (``max - value``: its minimum is displayed white), radiographs being
  displayed with attenuation bright and approximately log-encoded;
- the stand-in equals the line integral up to scale and offset, which the registration's
  similarity (NCC) ignores; each sequence is normalised to 0..1 by its 0.5 and 99.5
  percentiles within the exposed field;
- the exposed field: an image intensifier's round field or a collimator's shutters leave
  pixels that no beam reaches, at the no-signal value (the stand-in's highest attenuation) in
  every frame; those connected to the image's border are outside the field (``Frames.field``),
  which the registration leaves out (a dark implant inside the field is never taken for it);
- pixel spacing from Imager Pixel Spacing (0018,1164), else Pixel Spacing (0028,0030), else
  the caller's ``pixel_pitch_mm`` (a clear error when neither exists);
- frame times from Frame Time (0018,1063) or the Frame Time Vector (0018,1065), in seconds;
- the panel: a DICOM radiograph does not place its pixels in RTK's projection plane, so its
  geometry is read for a centred panel (recon.rtk_xml.PanelHeader.centered); an .mha stack's
  own header (origin, spacing, direction) places them.
"""

from __future__ import annotations

import glob
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import SimpleITK as sitk
from scipy.ndimage import label

from recon.dicom import has_dicom_preamble, open_dicom, series_files
from recon.io import ImageFileError, read_projections
from recon.rtk_xml import PanelHeader


@dataclass(frozen=True)
class Frames:
    """A fluoroscopy sequence ready to register.

    Attributes:
        data: float32 (F, rows, cols), line integrals (or their normalised stand-in).
        header: where the pixels lie in RTK's projection plane (pitch, origin, direction).
        times_s: frame times (F,) or None.
        photometric: "line integrals", "MONOCHROME1", "MONOCHROME2" or "images".
        stand_in: how the values became the line integral's stand-in, e.g.
            "-ln(value) (LIN, sign +1)" or "max - value (MONOCHROME1)".
        field: bool (rows, cols), the pixels the beam reaches; None: all of them.
    """

    data: np.ndarray
    header: PanelHeader
    times_s: np.ndarray | None
    photometric: str
    stand_in: str = "line integrals"
    field: np.ndarray | None = None

    @property
    def pixel_pitch_mm(self) -> tuple[float, float]:
        """Panel pitch (u, v), mm."""
        return self.header.spacing_mm


IMAGE_SUFFIXES = (".tif", ".tiff", ".png")
"""Frames as images (8 or 16 bit grey), e.g. a fluoroscopy unit's export or JTML's data."""
POLARITIES = ("dark", "bright")
"""How attenuation shows in images: dark (fluoroscopy's display) or bright (a radiograph's)."""


def blocks(image: np.ndarray, factor: int) -> np.ndarray:
    """``image`` (rows, cols) cut to whole ``factor`` x ``factor`` blocks, as a view (rows //
    factor, factor, cols // factor, factor): reduce over axes (1, 3) to bin it."""
    rows, cols = image.shape[0] // factor, image.shape[1] // factor
    return image[: rows * factor, : cols * factor].reshape(rows, factor, cols, factor)


def _tag(reader, key: str) -> str | None:
    return reader.GetMetaData(key).strip() if reader.HasMetaDataKey(key) else None


def _dicom_files(path: Path) -> list[str]:
    return series_files(path) if path.is_dir() else [str(path)]


def read_frames(
    path: str | Path | list[str | Path],
    pixel_pitch_mm: float | None = None,
    polarity: str = "dark",
) -> Frames:
    """Frames from an .mha/.mhd stack, a DICOM file or folder, or TIFF/PNG images (a file, a
    folder of them or a glob pattern, in sorted order; or a list of image files, in its
    order).

    Images carry no pixel size a registration can trust (a TIFF's resolution tag is a print
    size): ``pixel_pitch_mm`` gives it (e.g. the calibration's). Their ``polarity`` says how
    attenuation shows: "dark" (as fluoroscopy displays it: the implant darkest, the stand-in
    ``max - value``) or "bright" (as a radiograph: the value itself).

    Args:
        path: An .mha/.mhd stack, a DICOM file or folder, an image file, a folder of images,
            a glob pattern, or a list of image files.
        pixel_pitch_mm: The pixel size (mm) of images whose files do not give one.
        polarity: How attenuation shows in images: "dark" or "bright".

    Raises:
        FileNotFoundError: ``path`` does not exist (or the pattern matches nothing).
        ImageFileError: a file that is not a readable image (recon.io, recon.dicom).
        ValueError: naming the file and the tag: frames that are not grey-scale, of differing
            sizes or photometric interpretations, with NaN or infinite values, or with spacing
            or frame times that are not finite numbers; no pixel spacing and no
            ``pixel_pitch_mm``; an unknown polarity.
    """
    if polarity not in POLARITIES:
        raise ValueError(f"frames polarity {polarity!r}: one of {', '.join(POLARITIES)}")
    if isinstance(path, list | tuple):
        if len(path) == 1:
            path = path[0]
        else:
            files = [Path(p) for p in path]
            for name in files:
                if name.suffix.lower() not in IMAGE_SUFFIXES or not name.is_file():
                    raise FileNotFoundError(
                        f"{name}: a list of frames names TIFF or PNG files that exist"
                    )
            source = f"{files[0]} and {len(files) - 1} more"
            return _read_images(files, source, pixel_pitch_mm, polarity)
    images = _image_files(path)
    if images is not None:
        return _read_images(images, str(path), pixel_pitch_mm, polarity)
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file or folder")
    if path.suffix.lower() in (".mha", ".mhd"):
        stack = read_projections(path)
        return Frames(stack.data, stack.header, None, "line integrals")
    if path.is_file():
        with open(path, "rb") as fh:
            if not has_dicom_preamble(fh.read(132)):
                raise ValueError(
                    f"{path}: not frames this reads: give an .mha/.mhd stack, a DICOM file or "
                    f"folder, or {'/'.join(s.lstrip('.').upper() for s in IMAGE_SUFFIXES)} "
                    "images"
                )
    return _read_dicom(path, pixel_pitch_mm)


def _image_files(path: str | Path) -> list[Path] | None:
    """The TIFF/PNG files ``path`` names (a file, the images in a folder, or a glob pattern),
    sorted; None when it names none (a stack, DICOM)."""
    text = str(path)
    if any(c in text for c in "*?["):
        files = sorted(Path(p) for p in glob.glob(text))
        if not files:
            raise FileNotFoundError(f"{text}: the pattern matches no file")
        return files
    path = Path(path)
    if path.is_file():
        return [path] if path.suffix.lower() in IMAGE_SUFFIXES else None
    if path.is_dir():
        images = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        return images or None
    return None


def _read_images(
    files: list[Path], source: str, pixel_pitch_mm: float | None, polarity: str
) -> Frames:
    """Grey-scale TIFF/PNG frames (8 or 16 bit), one per file."""
    if pixel_pitch_mm is None:
        raise ValueError(
            f"{source}: images carry no pixel size to register with: give the panel's pixel "
            "pitch (the calibration's)"
        )
    arrays = []
    for name in files:
        try:
            image = sitk.ReadImage(str(name))
        except RuntimeError as err:
            raise ImageFileError(f"{name}: not a readable image ({err})") from None
        pixels = sitk.GetArrayFromImage(image).astype(np.float64)
        if image.GetNumberOfComponentsPerPixel() > 1:
            if not np.all(pixels == pixels[..., :1]):
                raise ValueError(f"{name}: a colour image; frames must be grey-scale")
            pixels = pixels[..., 0]
        pixels = pixels.reshape(-1, *pixels.shape[-2:])
        if arrays and pixels.shape[1:] != arrays[0].shape[1:]:
            raise ValueError(
                f"{name}: frames of {pixels.shape[1:]} pixels among frames of "
                f"{arrays[0].shape[1:]} (rows, columns)"
            )
        arrays.append(pixels)
    data = np.concatenate(arrays)
    if polarity == "dark":
        data, stand_in = data.max() - data, "max - value (images, attenuation dark)"
    else:
        stand_in = "value (images, attenuation bright)"
    pitch = float(pixel_pitch_mm)
    header = PanelHeader.centered(data.shape[1], data.shape[2], pitch, pitch, source=source)
    return _normalised(data, header, None, "images", stand_in, source)


def _read_dicom(path: Path, pixel_pitch_mm: float | None) -> Frames:
    """A DICOM file or a folder holding one series."""
    files = _dicom_files(path)
    arrays, times, spacing, photometric, stand_in = [], [], None, None, None
    for name in files:
        reader = open_dicom(name)
        try:
            image = reader.Execute()
        except RuntimeError as err:
            raise ImageFileError(f"{name}: not a readable DICOM image ({err})") from None
        kind = _tag(reader, "0028|0004")
        if kind not in ("MONOCHROME1", "MONOCHROME2"):
            raise ValueError(
                f"{name}: photometric interpretation {kind!r}; frames must be "
                "grey-scale (MONOCHROME1 or MONOCHROME2)"
            )
        if photometric not in (None, kind):
            raise ValueError(f"{name}: {kind} in a series of {photometric} images")
        photometric = kind
        pixels = sitk.GetArrayFromImage(image).astype(np.float64)
        pixels = pixels.reshape(-1, *pixels.shape[-2:])
        if arrays and pixels.shape[1:] != arrays[0].shape[1:]:
            raise ValueError(
                f"{name}: frames of {pixels.shape[1:]} pixels in a series of "
                f"{arrays[0].shape[1:]} (rows, columns)"
            )
        bad = pixels.size - int(np.count_nonzero(np.isfinite(pixels)))
        if bad:
            raise ValueError(f"{name}: {bad} pixels are NaN or infinite (after the rescale)")
        relation = (_tag(reader, "0028|1040") or "").upper(), _tag(reader, "0028|1041")
        how, attenuation = _stand_in(pixels, kind, *relation, name)
        if stand_in not in (None, how):
            raise ValueError(f"{name}: values are {how} in a series of {stand_in}")
        stand_in = how
        arrays.append(attenuation)
        spacing = spacing or _spacing(reader, name)
        times.extend(_times(reader, name, len(pixels), len(times)))
    data = np.concatenate(arrays)
    if spacing is None:
        if pixel_pitch_mm is None:
            raise ValueError(
                f"{path}: no pixel spacing in the DICOM header (0018,1164 or "
                "0028,0030); give the panel's pixel pitch explicitly"
            )
        spacing = (float(pixel_pitch_mm), float(pixel_pitch_mm))
    times_s = np.array(times) if len(times) == len(data) and None not in times else None
    header = PanelHeader.centered(data.shape[1], data.shape[2], *spacing, source=str(path))
    return _normalised(data, header, times_s, photometric, stand_in, str(path))


def _normalised(
    data: np.ndarray,
    header: PanelHeader,
    times_s: np.ndarray | None,
    photometric: str,
    stand_in: str,
    source: str,
) -> Frames:
    """The frames normalised to 0..1 by their 0.5 and 99.5 percentiles within the exposed
    field."""
    field = exposed_field(data)
    inside = data if field is None else data[:, field]
    low, high = np.percentile(inside, (0.5, 99.5))
    normalised = ((data - low) / max(high - low, 1e-12)).astype(np.float32)
    if not (np.isfinite(normalised).all() and (times_s is None or np.isfinite(times_s).all())):
        raise ValueError(f"{source}: pixel values or frame times overflow (beyond float range)")
    return Frames(normalised, header, times_s, photometric, stand_in, field)


def exposed_field(attenuation: np.ndarray) -> np.ndarray | None:
    """The pixels the beam reaches in a sequence (F, rows, cols) of line integrals or their
    stand-in: all but those at the sequence's highest value in every frame (no signal) that
    connect to the image's border. None when that leaves every pixel."""
    dark = np.all(attenuation == attenuation.max(), axis=0)
    if not dark.any():
        return None
    labels, _ = label(dark)
    edges = np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]])
    outside = np.isin(labels, np.unique(edges[edges > 0]))
    if not outside.any() or outside.all():
        return None
    return ~outside


def _stand_in(
    pixels: np.ndarray, photometric: str, relation: str, sign: str | None, name: str
) -> tuple[str, np.ndarray]:
    """How the values stand in for the line integral, and the values that do."""
    if relation in ("LIN", "LOG") and sign is not None:
        try:
            positive = {1: True, -1: False}[int(float(sign))]
        except (ValueError, KeyError, OverflowError):
            raise ValueError(
                f"{name}: Pixel Intensity Relationship Sign (0028,1041) is {sign!r}; "
                "DICOM allows +1 or -1"
            ) from None
        if not positive:
            return f"value ({relation}, sign -1)", pixels
        if relation == "LOG":
            return "-value (LOG, sign +1)", -pixels
        return "-ln(value) (LIN, sign +1)", -np.log(np.maximum(pixels, 1.0))
    if photometric == "MONOCHROME1":
        return "max - value (MONOCHROME1)", pixels.max() - pixels
    return "value (MONOCHROME2)", pixels


def _numbers(reader, key: str, name: str, count: int | None = None) -> list[float] | None:
    """The finite numbers of a multi-valued DICOM tag (at least ``count``), None when the tag
    is absent or empty; ValueError naming the file, the tag and its text otherwise."""
    text = _tag(reader, key)
    if not text:
        return None
    try:
        values = [float(x) for x in text.split("\\")]
    except ValueError:
        values = []
    if len(values) < (count or 1) or not all(np.isfinite(values)):
        raise ValueError(
            f"{name}: ({key.replace('|', ',')}) is {text!r}, not "
            f"{count or 'one or more'} finite numbers"
        )
    return values


def _spacing(reader, name: str) -> tuple[float, float] | None:
    for key in ("0018|1164", "0028|0030"):
        values = _numbers(reader, key, name, 2)
        if values:
            return (values[1], values[0])
    return None


def _times(reader, name: str, count: int, first: int) -> list[float | None]:
    """Times of ``count`` frames, the first being frame ``first`` of the sequence."""
    vector = _numbers(reader, "0018|1065", name)
    if vector:
        return list(np.cumsum(np.array(vector) / 1000.0)[:count])
    frame_ms = _numbers(reader, "0018|1063", name)
    if frame_ms:
        return list((first + np.arange(count)) * frame_ms[0] / 1000.0)
    return [None] * count

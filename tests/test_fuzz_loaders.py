"""Every reader of a user file, fed corrupted copies of a valid file.

Each test starts from a file our writers wrote (or a committed config), corrupts it with
hypothesis (byte flips, truncation, splices, numbers swapped for NaN, inf, huge, negative or
non-numbers, header fields and values given wrong values or types, pixels set to NaN or inf)
and checks that the reader either loads it, holding only finite numbers, or refuses it with
what the command line catches (``ValueError`` or ``OSError`` and their subclasses:
recon.io.ImageFileError, recon.config.ConfigError; scanner.study_folder.StudyError for study
folders) with the file named in the message. Nothing else may escape, no example may take
longer than :data:`DEADLINE`, and the address space is capped at what the process maps plus
:data:`HEADROOM_BYTES`, so a header claiming gigabytes of pixels must be refused before they
are allocated (an allocation failure reported by ITK fails the test too).

:data:`DEFAULT_EXAMPLES` inputs per reader run by default, :data:`SLOW_EXAMPLES` with
``-m slow``.
"""

from __future__ import annotations

import dataclasses
import faulthandler
import gzip
import json
import math
import re
import resource
import shutil
import struct
import zlib
from collections.abc import Callable
from datetime import timedelta
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from calibration.calibrate import corrected_geometry, plan_hash
from calibration.dewarp_grid import DewarpGridSpec
from calibration.phantom import BBPhantomSpec
from recon.config import load_config, load_protocol
from recon.dicom import read_dicom_series, write_dicom_series
from recon.distortion import Distortion
from recon.geometry import DetectorSpec, circular_orbit
from recon.io import read_projections, read_volume, write_projections, write_volume
from recon.rtk_xml import PanelHeader, read_rtk_geometry, write_rtk_geometry
from recon.static_volume import read_attenuation
from recon.volume import Volume, VolumeGrid
from registration.frames import read_frames
from registration.poses import BodyPose, read_poses, write_poses
from registration.settings import Settings
from scanner.inputs import load_backend_spec
from scanner.storage import ScanStore, ViewRecord
from scanner.study_folder import Study, StudyError
from sim.phantoms.knee import KneePhantomSpec
from sim.phantoms.tka import TkaPhantomSpec
from trajectories.config import ScannerConfig

DEFAULT_EXAMPLES = 100
"""Corrupted inputs per reader in the default suite."""
SLOW_EXAMPLES = 500
"""Corrupted inputs per reader under the ``slow`` marker."""
EXAMPLES = [
    pytest.param(DEFAULT_EXAMPLES, id=f"{DEFAULT_EXAMPLES}-examples"),
    pytest.param(SLOW_EXAMPLES, id=f"{SLOW_EXAMPLES}-examples", marks=pytest.mark.slow),
]
DEADLINE = timedelta(seconds=3)
"""Longest a reader may take on one small corrupted file."""
HANG_S = 600
"""A fuzz run still going after this long (s) is a hang: the process dumps its stack and exits."""
HEADROOM_BYTES = 2 << 30
"""Address space a reader may map beyond what the process maps before it runs."""
CONFIGS = Path(__file__).resolve().parents[1] / "configs"
CLEAR_ERRORS = (ValueError, OSError)
"""What study/cli.py catches and reports as the user's mistake."""


# -- the harness --------------------------------------------------------------------------------


def _mapped_bytes() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmSize:"):
            return int(line.split()[1]) * 1024
    raise AssertionError("no VmSize in /proc/self/status")


@pytest.fixture(autouse=True)
def bounded_address_space():
    """RLIMIT_AS at the current mapping plus HEADROOM_BYTES while a test runs."""
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    limit = _mapped_bytes() + HEADROOM_BYTES
    if hard != resource.RLIM_INFINITY:
        limit = min(limit, hard)
    resource.setrlimit(resource.RLIMIT_AS, (limit, hard))
    yield
    resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


def fuzz(examples: int, corrupted: st.SearchStrategy, check: Callable[[object], None]) -> None:
    """``check`` ``examples`` inputs drawn from ``corrupted``, each within DEADLINE."""
    seen = []

    @settings(
        max_examples=examples, deadline=DEADLINE, suppress_health_check=[HealthCheck.too_slow]
    )
    @given(corrupted)
    def run(value) -> None:
        seen.append(value)
        check(value)

    # hypothesis's deadline judges an example once it returns; a reader stuck in C++ (ITK once
    # hung on a MetaImage direction of 1e308) never does: dump where and end the run instead
    faulthandler.dump_traceback_later(HANG_S, exit=True)
    try:
        run()
    finally:
        faulthandler.cancel_dump_traceback_later()
    assert len(seen) >= examples, f"hypothesis ran {len(seen)} inputs, not {examples}"


def loads_or_refuses(load: Callable[[Path], object], path: Path, *, errors=CLEAR_ERRORS) -> None:
    """``load(path)`` returns something holding only finite numbers, or raises one of
    ``errors`` naming ``path``; any other exception propagates and fails the example."""
    try:
        loaded = load(path)
    except errors as err:
        message = str(err)
        assert str(path) in message, f"{type(err).__name__} does not name {path}: {message}"
        assert "allocate" not in message.lower(), f"tried to allocate the claimed size: {message}"
        return
    assert _all_finite(loaded), f"{path} loaded with non-finite numbers: {loaded!r:.300}"


def _all_finite(obj) -> bool:
    if isinstance(obj, np.ndarray):
        return obj.dtype.kind not in "fc" or bool(np.isfinite(obj).all())
    if isinstance(obj, float | np.floating):
        return math.isfinite(obj)
    if isinstance(obj, dict):
        return all(_all_finite(v) for v in obj.values())
    if isinstance(obj, list | tuple):
        return all(_all_finite(v) for v in obj)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return all(_all_finite(getattr(obj, f.name)) for f in dataclasses.fields(obj))
    if hasattr(obj, "model_dump"):
        return _all_finite(obj.model_dump())
    return True


# -- corruptions --------------------------------------------------------------------------------

WEIRD_NUMBERS = (
    "nan",
    "NaN",
    "inf",
    "-inf",
    "1e308",
    "-1e308",
    "1e999",
    "1e-320",
    "0",
    "-0",
    "-1",
    "65535",
    "2147483648",
    "4294967297",
    "99999999999999999999",
    "1.5",
    "0x10",
    "abc",
    "",
)
"""Text put where a number was: NaN, inf, huge, tiny, zero, negative, fractional, not one."""
_NUMBER = re.compile(rb"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")


@st.composite
def byte_flips(draw, data: bytes, start: int = 0) -> bytes:
    """1 to 8 bytes at or after ``start`` XORed with random non-zero bytes."""
    out = bytearray(data)
    for _ in range(draw(st.integers(1, 8))):
        out[draw(st.integers(start, len(data) - 1))] ^= draw(st.integers(1, 255))
    return bytes(out)


@st.composite
def splices(draw, data: bytes) -> bytes:
    """Up to 64 bytes cut out and up to 16 random ones put in their place."""
    a = draw(st.integers(0, len(data)))
    b = draw(st.integers(a, min(len(data), a + 64)))
    return data[:a] + draw(st.binary(max_size=16)) + data[b:]


def truncations(data: bytes) -> st.SearchStrategy[bytes]:
    return st.integers(0, len(data) - 1).map(lambda n: data[:n])


@st.composite
def number_swaps(draw, data: bytes, end: int | None = None) -> bytes:
    """1 to 3 numbers before ``end`` replaced by :data:`WEIRD_NUMBERS`."""
    spans = [m.span() for m in _NUMBER.finditer(data, 0, len(data) if end is None else end)]
    chosen = draw(st.lists(st.sampled_from(spans), min_size=1, max_size=3, unique=True))
    for a, b in sorted(chosen, reverse=True):
        data = data[:a] + draw(st.sampled_from(WEIRD_NUMBERS)).encode() + data[b:]
    return data


@st.composite
def float32_pokes(draw, data: bytes, start: int) -> bytes:
    """1 to 3 aligned float32 pixels at or after ``start`` set to NaN, inf or huge."""
    out = bytearray(data)
    slots = (len(data) - start) // 4
    for _ in range(draw(st.integers(1, 3))):
        k = start + 4 * draw(st.integers(0, slots - 1))
        value = draw(st.sampled_from((math.nan, math.inf, -math.inf, 3e38)))
        out[k : k + 4] = struct.pack("<f", value)
    return bytes(out)


def corruptions(data: bytes, text_end: int | None = None) -> st.SearchStrategy[bytes]:
    """Any of the generic corruptions; numbers are swapped in the first ``text_end`` bytes
    (none: binary files)."""
    generic = [byte_flips(data), truncations(data), splices(data)]
    if _NUMBER.search(data, 0, len(data) if text_end is None else text_end):
        generic.append(number_swaps(data, text_end))
    return st.one_of(*generic)


def _write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


# -- projection stacks and fluoroscopy frames (MetaImage) ----------------------------------------

_META_VALUES = {
    b"NDims": (b"2", b"4", b"0", b"-3", b"300"),
    b"BinaryData": (b"False", b"Maybe"),
    b"BinaryDataByteOrderMSB": (b"True",),
    b"CompressedData": (b"True",),
    b"ElementType": (b"MET_UCHAR", b"MET_DOUBLE", b"MET_FLOAT_ARRAY", b"MET_OTHER", b"float"),
    b"ElementDataFile": (b"LIST", b"missing.raw", b"/dev/zero", b"../../x.raw", b"x%03d.raw 0 9 1"),
    b"ElementNumberOfChannels": (b"3", b"0", b"-1", b"99999999"),
    b"HeaderSize": (b"-1", b"99999999", b"0", b"7"),
}


@st.composite
def meta_header_edits(draw, data: bytes) -> bytes:
    """A MetaImage header line given a wrong value, or a field added or dropped."""
    end = data.index(b"ElementDataFile")
    end = data.index(b"\n", end) + 1
    lines = data[:end].split(b"\n")[:-1]
    key = draw(st.sampled_from(sorted(_META_VALUES)))
    value = draw(st.sampled_from(_META_VALUES[key]))
    keys = [line.split(b"=")[0].strip() for line in lines]
    if key in keys and draw(st.booleans()):
        if draw(st.booleans()):
            lines[keys.index(key)] = key + b" = " + value
        else:
            del lines[keys.index(key)]
    else:
        lines.insert(draw(st.integers(0, len(lines) - 1)), key + b" = " + value)
    return b"\n".join(lines) + b"\n" + data[end:]


def _recompressed(header: bytes, pixels: bytes) -> bytes:
    """A compressed MetaImage of ``header`` and (raw) ``pixels``, CompressedDataSize updated."""
    packed = zlib.compress(pixels)
    header = re.sub(rb"CompressedDataSize = \d+", b"CompressedDataSize = %d" % len(packed), header)
    return header + packed


def _meta_corruptions(data: bytes) -> st.SearchStrategy[bytes]:
    """Generic corruptions, header edits, and NaN or inf pixels (in the decompressed pixels of
    a compressed file)."""
    pixels = data.index(b"\n", data.index(b"ElementDataFile")) + 1
    header, payload = data[:pixels], data[pixels:]
    if b"CompressedData = True" in header:
        raw = zlib.decompress(payload)
        pokes = float32_pokes(raw, 0).map(lambda b: _recompressed(header, b))
    else:
        pokes = float32_pokes(data, pixels)
    return st.one_of(corruptions(data, pixels), meta_header_edits(data), pokes)


@pytest.fixture(scope="module")
def stack_files(tmp_path_factory) -> dict[str, bytes]:
    """A small projection stack as .mha, as compressed .mha, and as .mhd + .raw."""
    folder = tmp_path_factory.mktemp("stacks")
    data = np.random.default_rng(0).uniform(0, 3, size=(3, 4, 5)).astype(np.float32)
    write_projections(folder / "s.mha", data, 0.5)
    write_projections(folder / "s.mhd", data, 0.5)
    image = sitk.ReadImage(str(folder / "s.mha"))
    sitk.WriteImage(image, str(folder / "z.mha"), useCompression=True)
    return {name: (folder / name).read_bytes() for name in ("s.mha", "z.mha", "s.mhd", "s.raw")}


@pytest.mark.parametrize("examples", EXAMPLES)
@pytest.mark.parametrize("name", ["s.mha", "z.mha"])
def test_projection_stacks(tmp_path, stack_files, name, examples) -> None:
    path = tmp_path / name
    fuzz(
        examples,
        _meta_corruptions(stack_files[name]),
        lambda corrupted: loads_or_refuses(read_projections, _write(path, corrupted)),
    )


@pytest.mark.parametrize("examples", EXAMPLES)
def test_projection_stacks_with_a_separate_data_file(tmp_path, stack_files, examples) -> None:
    header, raw = stack_files["s.mhd"], stack_files["s.raw"]
    corrupted = st.one_of(
        st.tuples(st.one_of(corruptions(header), meta_header_edits(header)), st.just(raw)),
        st.tuples(st.just(header), st.one_of(corruptions(raw), float32_pokes(raw, 0))),
    )

    def check(pair: tuple[bytes, bytes]) -> None:
        _write(tmp_path / "s.raw", pair[1])
        loads_or_refuses(read_projections, _write(tmp_path / "s.mhd", pair[0]))

    fuzz(examples, corrupted, check)


@pytest.mark.parametrize("examples", EXAMPLES)
def test_fluoroscopy_frame_stacks(tmp_path, stack_files, examples) -> None:
    path = tmp_path / "frames.mha"
    fuzz(
        examples,
        _meta_corruptions(stack_files["s.mha"]),
        lambda corrupted: loads_or_refuses(read_frames, _write(path, corrupted)),
    )


# -- RTK geometry XML -----------------------------------------------------------------------------

PANEL = DetectorSpec(rows=4, cols=5, pixel_pitch_mm=0.5)


@pytest.fixture(scope="module")
def geometry_xml(tmp_path_factory) -> bytes:
    path = tmp_path_factory.mktemp("xml") / "geometry.xml"
    write_rtk_geometry(path, circular_orbit(3, 500.0, 800.0, PANEL))
    return path.read_bytes()


_XML_EDITS = (
    b"<Projection>",
    b"</Projection>",
    b"<Matrix>1 2 3</Matrix>",
    b"<RadiusCylindricalDetector>100</RadiusCylindricalDetector>",
    b"<SourceToDetectorDistance>0</SourceToDetectorDistance>",
    b"<GantryAngle>nan</GantryAngle>",
    b"<Unknown/>",
    b'<!ENTITY a "aaaaaaaaaa">',
    b"&a;&a;&a;",
    b"\x00",
)


@st.composite
def xml_edits(draw, data: bytes) -> bytes:
    """An element, entity or byte put somewhere in the XML."""
    at = draw(st.integers(0, len(data)))
    return data[:at] + draw(st.sampled_from(_XML_EDITS)) + data[at:]


@pytest.mark.parametrize("examples", EXAMPLES)
def test_rtk_geometry_xml(tmp_path, geometry_xml, examples) -> None:
    header = PanelHeader.centered(PANEL.rows, PANEL.cols, PANEL.pixel_pitch_mm)
    path = tmp_path / "geometry.xml"
    fuzz(
        examples,
        st.one_of(corruptions(geometry_xml), xml_edits(geometry_xml)),
        lambda corrupted: loads_or_refuses(
            lambda p: read_rtk_geometry(p, header).matrices, _write(path, corrupted)
        ),
    )


# -- volumes and labels (NIfTI, MetaImage) --------------------------------------------------------

NIFTI_FIELDS = (
    *((40 + 2 * k, "<h") for k in range(8)),  # dim[0..7]
    (70, "<h"),  # datatype
    (72, "<h"),  # bitpix
    *((76 + 4 * k, "<f") for k in range(8)),  # pixdim[0..7]
    (108, "<f"),  # vox_offset
    (112, "<f"),  # scl_slope
    (116, "<f"),  # scl_inter
    (252, "<h"),  # qform_code
    (254, "<h"),  # sform_code
    *((256 + 4 * k, "<f") for k in range(6)),  # quatern_b, c, d, qoffset_x, y, z
    *((280 + 4 * k, "<f") for k in range(12)),  # srow_x, srow_y, srow_z
)
"""(byte offset, struct format) of the NIfTI-1 header fields that size and place the image."""
_WEIRD_SHORTS = (-32768, -1, 0, 1, 2, 3, 4, 7, 8, 16, 64, 255, 256, 1024, 32767)
_WEIRD_FLOATS = (math.nan, math.inf, -math.inf, 0.0, -0.0, 1e-45, 1e30, -1e30, 3e38, 0.5)


@st.composite
def nifti_field_edits(draw, data: bytes) -> bytes:
    """1 to 3 NIfTI header fields set to weird values."""
    out = bytearray(data)
    for _ in range(draw(st.integers(1, 3))):
        offset, fmt = draw(st.sampled_from(NIFTI_FIELDS))
        value = draw(st.sampled_from(_WEIRD_SHORTS if fmt == "<h" else _WEIRD_FLOATS))
        struct.pack_into(fmt, out, offset, value)
    return bytes(out)


def _nifti_corruptions(data: bytes, pixels_are_float: bool) -> st.SearchStrategy[bytes]:
    """Corruptions of a NIfTI file's bytes (``data`` uncompressed, 352-byte header)."""
    mutations = [corruptions(data, 0), nifti_field_edits(data)]
    if pixels_are_float:
        mutations.append(float32_pokes(data, 352))
    return st.one_of(*mutations)


def _volume_corruptions(name: str, files: dict[str, bytes]) -> st.SearchStrategy[bytes]:
    data = files[name]
    if name.endswith(".mha"):
        return _meta_corruptions(data)
    floats = not name.startswith("labels")
    if name.endswith(".nii"):
        return _nifti_corruptions(data, floats)
    inner = gzip.decompress(data)
    return st.one_of(
        corruptions(data, 0),
        _nifti_corruptions(inner, floats).map(lambda b: gzip.compress(b, mtime=0)),
    )


@pytest.fixture(scope="module")
def volume_files(tmp_path_factory) -> dict[str, bytes]:
    """A small 1/mm volume and its labels in every format read_volume reads."""
    grid = VolumeGrid((4, 5, 6), (0.5, 0.6, 0.7), (-1.0, 2.0, 30.0))
    mu = np.random.default_rng(1).uniform(0, 0.05, grid.shape).astype(np.float32)
    labels = (mu > 0.025).astype(np.uint8) * 3
    files = {}
    for suffix in (".nii", ".nii.gz", ".mha"):
        for stem, volume in (
            ("volume", Volume(mu, grid, "1/mm")),
            ("labels", Volume(labels, grid, "label")),
        ):
            folder = tmp_path_factory.mktemp(f"{stem}{suffix}")  # x.nii.gz beside x.nii
            path = write_volume(folder / f"{stem}{suffix}", volume)
            files[path.name] = path.read_bytes()
    return files


@pytest.mark.parametrize("examples", EXAMPLES)
@pytest.mark.parametrize("name", ["volume.nii", "volume.nii.gz", "volume.mha"])
def test_volumes(tmp_path, volume_files, name, examples) -> None:
    path = tmp_path / name
    fuzz(
        examples,
        _volume_corruptions(name, volume_files),
        lambda corrupted: loads_or_refuses(read_volume, _write(path, corrupted)),
    )


@pytest.mark.parametrize("examples", EXAMPLES)
@pytest.mark.parametrize("name", ["labels.nii", "labels.nii.gz", "labels.mha"])
def test_labels(tmp_path, volume_files, name, examples) -> None:
    path = tmp_path / name
    fuzz(
        examples,
        _volume_corruptions(name, volume_files),
        lambda corrupted: loads_or_refuses(
            lambda p: read_volume(p, unit="label"), _write(path, corrupted)
        ),
    )


@pytest.mark.parametrize("examples", EXAMPLES)
def test_static_scans(tmp_path, volume_files, examples) -> None:
    path = tmp_path / "volume.nii.gz"
    fuzz(
        examples,
        _volume_corruptions("volume.nii.gz", volume_files),
        lambda corrupted: loads_or_refuses(read_attenuation, _write(path, corrupted)),
    )


# -- DICOM: CT series and fluoroscopy -------------------------------------------------------------

_LONG_VRS = (b"OB", b"OW", b"OF", b"SQ", b"UT", b"UN")
_WEIRD_US = (0, 1, 2, 3, 7, 8, 12, 15, 16, 17, 32, 64, 4096, 65535)


def dicom_elements(data: bytes) -> list[tuple[int, bytes, int, int]]:
    """(value offset, VR, length field offset, length) of the top-level elements of an
    explicit-VR little-endian DICOM file, stopping at the first undefined length."""
    out, pos = [], 132  # preamble and "DICM"
    while pos + 8 <= len(data):
        vr = data[pos + 4 : pos + 6]
        if vr in _LONG_VRS:
            length, field, value = struct.unpack_from("<I", data, pos + 8)[0], pos + 8, pos + 12
        else:
            length, field, value = struct.unpack_from("<H", data, pos + 6)[0], pos + 6, pos + 8
        if length == 0xFFFFFFFF or value + length > len(data):
            break
        out.append((value, vr, field, length))
        pos = value + length
    return out


@st.composite
def dicom_value_edits(draw, data: bytes) -> bytes:
    """One element's value replaced: numbers (DS, IS) by weird ones, US by weird shorts, text
    by random text, the pixel data cut short; its length field follows."""
    value, vr, field, length = draw(st.sampled_from(dicom_elements(data)))
    if vr in (b"DS", b"IS"):
        parts = draw(st.lists(st.sampled_from(WEIRD_NUMBERS), min_size=1, max_size=4))
        new = "\\".join(parts).encode()
    elif vr == b"US":
        new = struct.pack("<H", draw(st.sampled_from(_WEIRD_US))) * max(1, length // 2)
    elif vr in _LONG_VRS:
        new = data[value : value + draw(st.integers(0, length))]
    else:
        new = draw(st.text(max_size=20)).encode("utf-8", "replace")
    new += b" " * (len(new) % 2)
    size_format = "<I" if vr in _LONG_VRS else "<H"
    head = bytearray(data[:value])
    struct.pack_into(size_format, head, field, len(new))
    return bytes(head) + new + data[value + length :]


@st.composite
def _series_corruption(draw, slices: list[bytes]) -> tuple[int, bytes]:
    k = draw(st.integers(0, len(slices) - 1))
    corrupted = draw(st.one_of(corruptions(slices[k], 0), dicom_value_edits(slices[k])))
    return k, corrupted


def _write_series(folder: Path, names: list[str], slices: list[bytes], k: int, data: bytes):
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir()
    for i, (name, content) in enumerate(zip(names, slices, strict=True)):
        (folder / name).write_bytes(data if i == k else content)
    return folder


@pytest.fixture(scope="module")
def ct_series(tmp_path_factory) -> tuple[list[str], list[bytes]]:
    folder = tmp_path_factory.mktemp("dicom") / "ct"
    grid = VolumeGrid((3, 5, 6), (0.5, 0.6, 0.7), (-1.0, 2.0, 30.0))
    hu = np.random.default_rng(2).uniform(-1000, 1500, grid.shape).astype(np.float32)
    paths = write_dicom_series(folder, Volume(hu, grid, "HU"), 0.02)
    return [p.name for p in paths], [p.read_bytes() for p in paths]


@pytest.mark.parametrize("examples", EXAMPLES)
def test_dicom_ct_series(tmp_path, ct_series, examples) -> None:
    names, slices = ct_series
    fuzz(
        examples,
        _series_corruption(slices),
        lambda corrupted: loads_or_refuses(
            read_dicom_series, _write_series(tmp_path / "ct", names, slices, *corrupted)
        ),
    )


@pytest.fixture(scope="module")
def fluoro_dicom(tmp_path_factory) -> tuple[list[str], list[bytes]]:
    """Three RF frames as single DICOM files (one series)."""
    folder = tmp_path_factory.mktemp("fluoro")
    stack = np.random.default_rng(3).integers(100, 4000, size=(3, 6, 7)).astype(np.uint16)
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    names = []
    for k, image in enumerate(stack):
        item = sitk.GetImageFromArray(image)
        item.SetSpacing((0.25, 0.3))
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
        names.append(f"frame{k}.dcm")
        writer.SetFileName(str(folder / names[-1]))
        writer.Execute(item)
    return names, [(folder / name).read_bytes() for name in names]


@pytest.mark.parametrize("examples", EXAMPLES)
def test_dicom_fluoroscopy_file(tmp_path, fluoro_dicom, examples) -> None:
    first = fluoro_dicom[1][0]
    path = tmp_path / "frame.dcm"
    fuzz(
        examples,
        st.one_of(corruptions(first, 0), dicom_value_edits(first)),
        lambda corrupted: loads_or_refuses(read_frames, _write(path, corrupted)),
    )


@pytest.mark.parametrize("examples", EXAMPLES)
def test_dicom_fluoroscopy_folder(tmp_path, fluoro_dicom, examples) -> None:
    names, slices = fluoro_dicom
    fuzz(
        examples,
        _series_corruption(slices),
        lambda corrupted: loads_or_refuses(
            read_frames, _write_series(tmp_path / "frames", names, slices, *corrupted)
        ),
    )


# -- poses.csv -----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def poses_csv(tmp_path_factory) -> bytes:
    path = tmp_path_factory.mktemp("poses") / "poses.csv"
    T = np.eye(4)
    T[:3, 3] = (1.0, -2.0, 3.5)
    poses = [BodyPose(f, b, T, 0.9, 0.4) for f in (0, 1) for b in ("femur", "tibia")]
    write_poses(path, poses, {"femur": np.zeros(3), "tibia": np.ones(3)})
    return path.read_bytes()


_CSV_FIELDS = ("nan", "inf", "", "x", "1e999", "[1, 2]", '"a,b"', "\x00", "1,2", "\n")


@st.composite
def csv_field_edits(draw, data: bytes) -> bytes:
    """A field (header or value) replaced by a wrong type, NaN, a quote, a NUL or a newline."""
    lines = data.decode().split("\r\n")
    row = draw(st.integers(0, len(lines) - 2))
    fields = lines[row].split(",")
    fields[draw(st.integers(0, len(fields) - 1))] = draw(st.sampled_from(_CSV_FIELDS))
    lines[row] = ",".join(fields)
    return "\r\n".join(lines).encode()


def _poses_read(path: Path) -> list:
    """read_poses' poses without their similarity and seconds: NaN there means unknown."""
    return [(pose.frame, pose.body, pose.T_world_body) for pose in read_poses(path)]


@pytest.mark.parametrize("examples", EXAMPLES)
def test_poses_csv(tmp_path, poses_csv, examples) -> None:
    path = tmp_path / "poses.csv"
    fuzz(
        examples,
        st.one_of(corruptions(poses_csv), csv_field_edits(poses_csv)),
        lambda corrupted: loads_or_refuses(_poses_read, _write(path, corrupted)),
    )


# -- YAML configs --------------------------------------------------------------------------------

YAML_CONFIGS: dict[str, Callable[[Path], object]] = {
    "protocols/calibration_spiral.yaml": load_protocol,
    "protocols/demo_knee.yaml": load_protocol,
    "protocols/knee_fluoroscopy_lateral.yaml": load_protocol,
    "protocols/knee_reverse_spiral_180.yaml": load_protocol,
    "protocols/knee_reverse_spiral_360.yaml": load_protocol,
    "protocols/knee_reverse_spiral_360_quarter_dose.yaml": load_protocol,
    "protocols/knee_reverse_spiral_360_sparse90.yaml": load_protocol,
    "backends/sim.yaml": lambda p: load_backend_spec("sim", p),
    "backends/ur.yaml": lambda p: load_backend_spec("ur", p),
    "scanner.yaml": lambda p: load_config(p, ScannerConfig),
    "registration.yaml": lambda p: load_config(p, Settings),
    "registration_implants.yaml": lambda p: load_config(p, Settings),
    "registration_gait.yaml": lambda p: load_config(p, Settings),
    "phantoms/knee.yaml": lambda p: load_config(p, KneePhantomSpec),
    "phantoms/bb_helix.yaml": lambda p: load_config(p, BBPhantomSpec),
    "phantoms/dewarp_grid.yaml": lambda p: load_config(p, DewarpGridSpec),
    "phantoms/tka.yaml": lambda p: load_config(p, TkaPhantomSpec),
}
"""Each committed config and the function the package that owns it reads it with."""


WRONG_VALUES = st.one_of(
    st.none(),
    st.booleans(),
    st.sampled_from((0, -1, 2**31, 2**63, 10**30)),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=8),
    st.lists(st.integers(-3, 3), max_size=4),
    st.dictionaries(st.text(max_size=4), st.integers(), max_size=2),
)
"""A value of the wrong type, or of the right type and a wrong size."""


def _paths(tree, prefix=()) -> list[tuple]:
    out = [prefix]
    if isinstance(tree, dict):
        for key, value in tree.items():
            out += _paths(value, (*prefix, key))
    elif isinstance(tree, list):
        for i, value in enumerate(tree):
            out += _paths(value, (*prefix, i))
    return out


def _edited(draw, tree, paths: list[tuple]):
    """``tree`` with the value at one of ``paths`` (the root for ``()``) given a wrong value,
    removed, or joined by an unknown key."""
    path = draw(st.sampled_from(paths))
    if not path:
        return draw(WRONG_VALUES)
    parent = tree
    for key in path[:-1]:
        parent = parent[key]
    action = draw(st.sampled_from(("replace", "delete", "add")))
    if action == "replace" or not isinstance(parent, dict):
        parent[path[-1]] = draw(WRONG_VALUES)
    elif action == "delete":
        del parent[path[-1]]
    else:
        parent["unknown_field"] = draw(WRONG_VALUES)
    return tree


@st.composite
def yaml_field_edits(draw, text: bytes) -> bytes:
    """A field given a wrong value, removed, or joined by an unknown field."""
    tree = yaml.safe_load(text)
    return yaml.safe_dump(_edited(draw, tree, _paths(tree)[1:])).encode()


@pytest.mark.parametrize("examples", EXAMPLES)
@pytest.mark.parametrize("name", sorted(YAML_CONFIGS))
def test_yaml_configs(tmp_path, name, examples) -> None:
    text = (CONFIGS / name).read_bytes()
    for sibling in (CONFIGS / name).parent.glob("*.yaml"):  # what a config ``extends``
        (tmp_path / sibling.name).write_bytes(sibling.read_bytes())
    path = tmp_path / Path(name).name
    fuzz(
        examples,
        st.one_of(corruptions(text), yaml_field_edits(text)),
        lambda corrupted: loads_or_refuses(YAML_CONFIGS[name], _write(path, corrupted)),
    )


def test_every_committed_config_is_fuzzed() -> None:
    committed = {p.relative_to(CONFIGS).as_posix() for p in CONFIGS.rglob("*.yaml")}
    assert committed == set(YAML_CONFIGS)


# -- JSON written beside the data: the study manifest, a panel's distortion ----------------------


@pytest.fixture(scope="module")
def json_files(tmp_path_factory) -> dict[str, bytes]:
    folder = tmp_path_factory.mktemp("json")
    study = Study.create(folder / "study", {"protocol": {"name": "demo", "views": 3}})
    study.mark("plan", "complete", views=3)
    warp = Distortion(300.0, 300.0, 2, np.arange(12.0).reshape(2, 6) * 1e-3, 0.1, 0.2, 40)
    return {
        "study.json": (folder / "study" / "study.json").read_bytes(),
        "distortion.json": warp.write(folder / "distortion.json").read_bytes(),
    }


@st.composite
def json_value_edits(draw, text: bytes) -> bytes:
    """A JSON value (or the whole document) replaced by one of the wrong type, removed, or
    joined by an unknown key."""
    tree = json.loads(text)
    return json.dumps(_edited(draw, tree, _paths(tree))).encode()


@pytest.mark.parametrize("examples", EXAMPLES)
def test_study_manifests(tmp_path, json_files, examples) -> None:
    text = json_files["study.json"]

    def check(corrupted: bytes) -> None:
        _write(tmp_path / "study.json", corrupted)
        loads_or_refuses(Study.open, tmp_path, errors=(*CLEAR_ERRORS, StudyError))

    fuzz(examples, st.one_of(corruptions(text), json_value_edits(text)), check)


@pytest.mark.parametrize("examples", EXAMPLES)
def test_distortions(tmp_path, json_files, examples) -> None:
    text = json_files["distortion.json"]
    path = tmp_path / "distortion.json"
    fuzz(
        examples,
        st.one_of(corruptions(text), json_value_edits(text)),
        lambda corrupted: loads_or_refuses(Distortion.read, _write(path, corrupted)),
    )


@pytest.fixture(scope="module")
def scan_study(tmp_path_factory) -> Path:
    """A study holding one acquired view of a two-view scan."""
    folder = tmp_path_factory.mktemp("scan") / "study"
    study = Study.create(folder, {})
    planned = circular_orbit(2, 500.0, 800.0, PANEL)
    store = ScanStore(study, PANEL, ("lift", "shoulder"), 2, planned)
    view = planned[0]
    record = ViewRecord(0, 0.0, 1.0, 1.0, np.zeros(2), view.matrix, view.source_mm, 70, 10, 5, 1)
    store.put(record, np.zeros((4, 5), np.float32), np.ones((4, 5), np.float32))
    study.save()
    return folder


def _reopen_scan(folder: Path) -> dict:
    return ScanStore(
        Study.open(folder), PANEL, ("lift", "shoulder"), 2, circular_orbit(2, 500.0, 800.0, PANEL)
    ).records


@pytest.mark.parametrize("examples", EXAMPLES)
def test_view_records_of_a_scan(tmp_path, scan_study, examples) -> None:
    """Resuming a scan rereads its view records: checked against the manifest's sha256, or,
    when the manifest was saved before the record (a crash), on their own."""
    text = (scan_study / "scan" / "views" / "view_0000.json").read_bytes()
    folder = tmp_path / "study"

    def check(case: tuple[bytes, bool]) -> None:
        corrupted, crashed = case
        if folder.exists():
            shutil.rmtree(folder)
        shutil.copytree(scan_study, folder)
        _write(folder / "scan" / "views" / "view_0000.json", corrupted)
        if crashed:
            manifest = json.loads((folder / "study.json").read_text())
            del manifest["files"]["scan/views/view_0000.json"]
            (folder / "study.json").write_text(json.dumps(manifest))
        loads_or_refuses(_reopen_scan, folder, errors=(*CLEAR_ERRORS, StudyError))

    fuzz(
        examples,
        st.tuples(st.one_of(corruptions(text), json_value_edits(text)), st.booleans()),
        check,
    )


@pytest.fixture(scope="module")
def calibration_folder(tmp_path_factory) -> tuple[Path, object]:
    """A calibration of configs/protocols/calibration_spiral.yaml: report.json and its views."""
    protocol = load_protocol(CONFIGS / "protocols" / "calibration_spiral.yaml")
    folder = tmp_path_factory.mktemp("calibration")
    d = protocol.detector
    write_rtk_geometry(folder / "geometry.xml", circular_orbit(3, 500.0, 800.0, d))
    summary = {"protocol": protocol.name, "plan_hash": plan_hash(protocol), "views": 3}
    (folder / "report.json").write_text(json.dumps({"summary": summary, "views": []}))
    return folder, protocol


@pytest.mark.parametrize("examples", EXAMPLES)
def test_calibration_reports(tmp_path, calibration_folder, examples) -> None:
    """A calibration's report.json, read to match it to the scan it corrects."""
    original, protocol = calibration_folder
    text = (original / "report.json").read_bytes()
    folder = tmp_path / "calibration"
    shutil.copytree(original, folder, dirs_exist_ok=True)

    def check(corrupted: bytes) -> None:
        _write(folder / "report.json", corrupted)
        loads_or_refuses(lambda p: corrected_geometry(p, protocol).matrices, folder)

    fuzz(examples, st.one_of(corruptions(text), json_value_edits(text)), check)


def test_the_address_space_is_capped() -> None:
    with pytest.raises(MemoryError):
        np.empty(2 * HEADROOM_BYTES, np.uint8)


def test_the_harness_catches_an_unclear_error(tmp_path) -> None:
    def careless(path: Path) -> None:
        raise ValueError("bad number")

    with pytest.raises(AssertionError, match="does not name"):
        loads_or_refuses(careless, tmp_path / "x.yaml")
    with pytest.raises(AssertionError, match="non-finite"):
        loads_or_refuses(lambda p: {"x": [1.0, math.nan]}, tmp_path / "x.yaml")

"""recon.rtk_xml against the peer itk-rtk: geometries cross between the toolkits intact."""

from __future__ import annotations

import itk
import numpy as np
import pytest
from itk import RTK as rtk

from recon.geometry import DetectorSpec, View, helical_orbit
from recon.rtk_xml import centered_origin_uv_mm, read_rtk_geometry, write_rtk_geometry

PANEL = DetectorSpec(rows=40, cols=56, pixel_pitch_mm=0.8)
POINTS = np.random.default_rng(0).normal(size=(25, 3)) * 60 + [0, 0, 480]


def rtk_pixels(rtk_geometry, i: int, origin_uv_mm) -> np.ndarray:
    """Pixel indices of POINTS through RTK's own matrix of projection i."""
    m = itk.array_from_vnl_matrix(rtk_geometry.GetMatrix(i).GetVnlMatrix().as_matrix())
    h = POINTS @ m[:, :3].T + m[:, 3]
    return (h[:, :2] / h[:, 2:3] - origin_uv_mm) / PANEL.pixel_pitch_mm


def read_with_rtk(path):
    reader = rtk.ThreeDCircularProjectionGeometryXMLFileReader.New()
    reader.SetFilename(str(path))
    reader.GenerateOutputInformation()
    return reader.GetOutputObject()


def test_a_geometry_we_write_gives_rtk_the_same_projections(tmp_path):
    geometry = helical_orbit(
        12, 600, 1000, PANEL, arc_deg=360, z_start_mm=420, z_end_mm=540, passes=2, start_deg=17
    )
    origin = (-20.0, -14.0)
    path = write_rtk_geometry(tmp_path / "g.xml", geometry, origin_uv_mm=origin)
    theirs = read_with_rtk(path)
    assert len(theirs.GetGantryAngles()) == 12
    for i, view in enumerate(geometry):
        np.testing.assert_allclose(rtk_pixels(theirs, i, origin), view.project(POINTS), atol=1e-8)
    assert read_rtk_geometry(path, PANEL, origin) == geometry


def test_a_geometry_rtk_writes_reads_back_as_the_same_projections(tmp_path):
    rng = np.random.default_rng(7)
    theirs = rtk.ThreeDCircularProjectionGeometry.New()
    for _ in range(8):
        # sid, sdd, gantry, projection offset x/y, out of plane, in plane, source offset x/y
        params = [
            600 + rng.normal() * 5,
            1000 + rng.normal() * 5,
            rng.uniform(0, 360),
            *rng.normal(size=2) * 3,
            *rng.normal(size=2) * 4,
            *rng.normal(size=2) * 3,
        ]
        theirs.AddProjection(*[float(p) for p in params])
    writer = rtk.ThreeDCircularProjectionGeometryXMLFileWriter.New()
    writer.SetFilename(str(tmp_path / "rtk.xml"))
    writer.SetObject(theirs)
    writer.WriteFile()
    ours = read_rtk_geometry(tmp_path / "rtk.xml", PANEL)
    origin = centered_origin_uv_mm(PANEL.rows, PANEL.cols, 0.8, 0.8)
    for i, view in enumerate(ours):
        np.testing.assert_allclose(view.project(POINTS), rtk_pixels(theirs, i, origin), atol=1e-8)


BAD = {
    "version": (
        '<RTKThreeDCircularGeometry version="2"><Projection/></RTKThreeDCircularGeometry>',
        "only 3 is read",
    ),
    "element": (
        '<RTKThreeDCircularGeometry version="3"><Projection><Bogus>1</Bogus>'
        "</Projection></RTKThreeDCircularGeometry>",
        "unknown element <Bogus>",
    ),
    "number": (
        '<RTKThreeDCircularGeometry version="3"><SourceToIsocenterDistance>abc'
        "</SourceToIsocenterDistance><Projection/></RTKThreeDCircularGeometry>",
        "not a number",
    ),
    "cylindrical": (
        '<RTKThreeDCircularGeometry version="3"><SourceToIsocenterDistance>600'
        "</SourceToIsocenterDistance><SourceToDetectorDistance>1000"
        "</SourceToDetectorDistance><RadiusCylindricalDetector>1000"
        "</RadiusCylindricalDetector><Projection/></RTKThreeDCircularGeometry>",
        "cylindrical",
    ),
    "empty": (
        '<RTKThreeDCircularGeometry version="3"></RTKThreeDCircularGeometry>',
        "no <Projection>",
    ),
    "truncated": ('<RTKThreeDCircularGeometry version="3"><Projection>', "not valid XML"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_malformed_files_are_refused_with_the_file_named(tmp_path, case):
    text, message = BAD[case]
    path = tmp_path / f"{case}.xml"
    path.write_text(text)
    with pytest.raises(ValueError, match=message) as info:
        read_rtk_geometry(path, PANEL)
    assert str(path) in str(info.value)


def test_a_stored_matrix_that_disagrees_with_its_parameters_is_refused(tmp_path):
    geometry = helical_orbit(3, 600, 1000, PANEL, arc_deg=90, z_start_mm=0, z_end_mm=0)
    path = write_rtk_geometry(tmp_path / "g.xml", geometry)
    text = path.read_text(encoding="utf-8").replace("<GantryAngle>", "<GantryAngle>1", 1)
    path.write_text(text)
    with pytest.raises(ValueError, match="projection 0: stored <Matrix> disagrees"):
        read_rtk_geometry(path, PANEL)


def test_missing_file_and_mixed_pitch(tmp_path):
    with pytest.raises(FileNotFoundError, match="no such geometry file"):
        read_rtk_geometry(tmp_path / "absent.xml", PANEL)
    g = helical_orbit(2, 600, 1000, PANEL, arc_deg=90, z_start_mm=0, z_end_mm=0)
    odd = View(g[1].source_mm, g[1].detector_origin_mm, g[1].e_u, g[1].e_v, 0.9, 0.8, 40, 56)
    with pytest.raises(ValueError, match="view 1 has pitch"):
        write_rtk_geometry(tmp_path / "g.xml", type(g)([g[0], odd]))

"""An RTK-format scan, written and read back: the projection stack (.mha) and its geometry (RTK
XML) as any RTK program writes them, reconstructed with weighted FDK.

Prints what was read and the reconstruction's value inside the phantom's brain (0.2 /mm).
"""

import tempfile
from pathlib import Path

from recon import (
    DetectorSpec,
    VolumeGrid,
    circular_orbit,
    fdk_reconstruct,
    read_projections,
    read_rtk_geometry,
    write_projections,
    write_rtk_geometry,
)
from sim.phantoms import project_ellipsoids, shepp_logan_3d

with tempfile.TemporaryDirectory() as folder:
    views = circular_orbit(120, 600.0, 1000.0, DetectorSpec(rows=96, cols=96, pixel_pitch_mm=2.0))
    projections = project_ellipsoids(shepp_logan_3d(60.0), views)
    write_projections(Path(folder) / "projections.mha", projections, 2.0)
    write_rtk_geometry(Path(folder) / "geometry.xml", views)
    # what a user with an RTK scan does: read the stack, then its geometry against its header
    stack = read_projections(Path(folder) / "projections.mha")
    geometry = read_rtk_geometry(Path(folder) / "geometry.xml", stack.header)
grid = VolumeGrid.centered((64, 64, 64), 1.5, (0.0, 0.0, 0.0))
volume = fdk_reconstruct(stack.data, geometry, grid).volume
brain = volume.data[32, 26:38, 26:38].mean()
print(f"{len(geometry)} views of {geometry.rows} x {geometry.cols}; brain {brain:.3f} /mm")

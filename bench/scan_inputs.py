"""A reconstruction benchmark's inputs on disk, as each worker process reads them: the
projection stack (projections.mha), its RTK geometry (geometry.xml) and the grid (grid.json)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from recon.geometry import Geometry
from recon.volume import VolumeGrid


def write_scan(folder: Path, projections: np.ndarray, geometry: Geometry, grid: VolumeGrid) -> None:
    """Write ``projections`` through ``geometry`` and the grid to reconstruct on into the new
    ``folder``."""
    from recon.io import write_projections
    from recon.rtk_xml import write_rtk_geometry

    folder.mkdir(parents=True)
    write_projections(folder / "projections.mha", projections, geometry[0].pitch_u_mm)
    write_rtk_geometry(folder / "geometry.xml", geometry)
    (folder / "grid.json").write_text(
        json.dumps(
            {"shape": grid.shape, "spacing_mm": grid.spacing_mm, "origin_mm": grid.origin_mm}
        )
    )


def read_scan(folder: Path) -> tuple[np.ndarray, Geometry, VolumeGrid]:
    """The projections, geometry and grid :func:`write_scan` wrote into ``folder``."""
    from recon.io import read_projections
    from recon.rtk_xml import read_rtk_geometry

    stack = read_projections(folder / "projections.mha")
    geometry = read_rtk_geometry(folder / "geometry.xml", stack.header)
    spec = json.loads((folder / "grid.json").read_text())
    grid = VolumeGrid(tuple(spec["shape"]), tuple(spec["spacing_mm"]), tuple(spec["origin_mm"]))
    return stack.data, geometry, grid

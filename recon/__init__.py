"""Cone-beam CT geometry, projectors, weighted FDK and the file formats (volumes, projection
stacks, RTK XML).

The public names below load their module on first use::

    import recon
    views = recon.circular_orbit(180, 600.0, 1000.0, recon.DetectorSpec(rows=128, cols=128,
                                 pixel_pitch_mm=1.5))
    volume = recon.fdk_reconstruct(projections, views, recon.VolumeGrid.centered(...)).volume
"""

import os

from recon._exports import lazy

# OpenMP threads (numba's parallel kernels, Pinocchio's) sleep when their work is done instead
# of spinning for it: a spinning thread takes the core another process needs, and tracking
# beside another run slowed 4.5x (26 -> 116 s) where passive waiting costs 1.2x; alone, waking
# the threads costs 4 % (bones) to 17 % (components' meshes) of tracking (docs/design.md,
# "Threads"). libgomp reads this once, when it loads: every package that may load it imports
# recon first. Set OMP_WAIT_POLICY=active to spin on a dedicated box.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

_EXPORTS = {
    "DetectorSpec": "recon.geometry",
    "View": "recon.geometry",
    "Geometry": "recon.geometry",
    "circular_orbit": "recon.geometry",
    "helical_orbit": "recon.geometry",
    "short_scan_arc_deg": "recon.geometry",
    "Volume": "recon.volume",
    "VolumeGrid": "recon.volume",
    "JosephProjector": "recon.project",
    "forward_project": "recon.project",
    "backproject": "recon.project",
    "FDKResult": "recon.fdk",
    "fdk_reconstruct": "recon.fdk",
    "IterativeSettings": "recon.iterative",
    "IterativeResult": "recon.iterative",
    "iterative_reconstruct": "recon.iterative",
    "ProjectionStack": "recon.io",
    "read_volume": "recon.io",
    "write_volume": "recon.io",
    "read_projections": "recon.io",
    "write_projections": "recon.io",
    "read_stack_header": "recon.io",
    "PanelHeader": "recon.rtk_xml",
    "read_rtk_geometry": "recon.rtk_xml",
    "write_rtk_geometry": "recon.rtk_xml",
    "ScanProtocol": "recon.config",
    "load_config": "recon.config",
    "load_protocol": "recon.config",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy(__name__, _EXPORTS)

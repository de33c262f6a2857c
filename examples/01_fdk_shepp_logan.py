"""FDK of the 3D Shepp-Logan phantom: analytic projections on a circular orbit, reconstructed.

The README's example. Prints the volume's shape and the brain's mean (0.2 in the modified
phantom's units).
"""

from recon.fdk import fdk_reconstruct
from recon.geometry import DetectorSpec, circular_orbit
from recon.volume import VolumeGrid
from sim.phantoms.ellipsoids import project_ellipsoids, shepp_logan_3d

phantom = shepp_logan_3d(scale_mm=60.0)  # 10 ellipsoids, values per mm
panel = DetectorSpec(rows=96, cols=96, pixel_pitch_mm=2.0)
views = circular_orbit(120, 600.0, 1000.0, panel)  # 120 views, source 600 mm from the axis
grid = VolumeGrid.centered((64, 64, 64), 1.5, (0.0, 0.0, 0.0))
volume = fdk_reconstruct(project_ellipsoids(phantom, views), views, grid).volume
print(volume.data.shape, f"brain {volume.data[32, 26:38, 26:38].mean():.3f} (0.2)")

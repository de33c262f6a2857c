"""Segment files: a static scan's bones labelled, and a surface mesh per bone."""

from __future__ import annotations

from pathlib import Path

from recon.attenuation import DEFAULT_EFFECTIVE_ENERGY_KEV
from recon.io import write_volume
from recon.static_volume import StaticUnit, read_attenuation
from recon.volume import Volume
from registration.segment import bone_surfaces, segment_bones


def segment_files(
    volume_path: Path,
    out: Path,
    *,
    unit: StaticUnit | None = None,
    side: str | None = None,
    effective_energy_kev: float = DEFAULT_EFFECTIVE_ENERGY_KEV,
    meshes: Path | None = None,
) -> Volume:
    """``cbct segment``: label the bones of a static knee scan as the demo does.

    Args:
        volume_path: The scan: a volume file or a DICOM CT series folder, in HU or 1/mm.
        out: The new label volume (registration.labels: air 0, soft tissue 1, femur 2,
            tibia 3, fibula 4, patella 5).
        unit: The scan's unit where its file does not say.
        side: "right" or "left"; inferred from the fibula when None.
        effective_energy_kev: Effective energy (keV) HU are converted to 1/mm at.
        meshes: A new folder for one surface (STL, world mm) per bone, or None.

    Returns:
        The labels.
    """
    for path in (out, meshes):
        if path is not None and path.exists():
            raise FileExistsError(f"{path} exists: nothing is overwritten")
    volume, _ = read_attenuation(volume_path, unit, effective_energy_kev)
    labels = segment_bones(volume, side=side)
    write_volume(out, labels)
    if meshes is not None:
        meshes.mkdir(parents=True)
        for name, mesh in bone_surfaces(labels).items():
            mesh.export(meshes / f"{name}.stl")
    return labels

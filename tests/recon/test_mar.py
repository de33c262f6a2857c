"""Normalised metal artefact reduction (recon.mar) on a polychromatic scan of metal in water:
the metal found, its streaks reduced, and too much metal or none refused."""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from recon.fdk import fdk_reconstruct
from recon.geometry import DetectorSpec, circular_orbit
from recon.io import read_volume, write_projections
from recon.mar import nmar
from recon.project import JosephProjector
from recon.rtk_xml import write_rtk_geometry
from recon.volume import VolumeGrid
from sim.spectrum import COMPOSITIONS, tube_spectrum
from study.cli import app

GRID = VolumeGrid.centered((64, 64, 24), 1.5)
GEOMETRY = circular_orbit(120, 600.0, 1000.0, DetectorSpec(rows=40, cols=96, pixel_pitch_mm=2.0))


def _phantom(metal_radius_mm: float) -> dict[str, np.ndarray]:
    """Each material's share of every voxel: a water cylinder of radius 40 mm, two bone rods
    and two metal rods of ``metal_radius_mm`` (0: none), supersampled 3 x 3 across."""
    s = 3
    offsets = (np.arange(s) + 0.5) / s - 0.5
    x = GRID.origin_mm[0] + GRID.spacing_mm[0] * (np.arange(64)[:, None] + offsets).ravel()
    xx, yy = np.meshgrid(x, x, indexing="xy")

    def disc(cx: float, cy: float, r: float) -> np.ndarray:
        inside = ((xx - cx) ** 2 + (yy - cy) ** 2 <= r * r).astype(np.float32)
        return inside.reshape(64, s, 64, s).mean(axis=(1, 3))

    metal = disc(-14, 4, metal_radius_mm) + disc(14, 4, metal_radius_mm)
    bone = (disc(0, -22, 8) + disc(0, 24, 6)) * (1 - metal)
    water = disc(0, 0, 40) - metal - bone
    return {
        name: np.broadcast_to(share, GRID.shape).astype(np.float32)
        for name, share in (("water", water), ("cortical_bone", bone), ("CoCr", metal))
    }


def _scan(shares: dict[str, np.ndarray], seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Polychromatic line integrals with the photons' noise, and the truth's attenuation."""
    spectrum = tube_spectrum(110.0)
    lengths = np.stack([JosephProjector(v, GRID).project(GEOMETRY) for v in shares.values()])
    mu = np.stack([COMPOSITIONS[n].mu_per_mm(spectrum.energies_kev) for n in shares])
    shown = spectrum.transmission(mu, lengths)
    counts = np.maximum(np.random.default_rng(seed).poisson(1e5 * shown), 1)
    beam = spectrum.hardened("water", 60.0)
    truth = sum(beam.mean_mu_per_mm(n) * v for n, v in shares.items())
    return (-np.log(counts / 1e5)).astype(np.float32), truth


def _rmse_outside(volume: np.ndarray, truth: np.ndarray, metal: np.ndarray) -> float:
    inside = (truth > 0.005) & (metal < 0.01)
    return float(np.sqrt(np.mean((volume[inside] - truth[inside]) ** 2)))


@pytest.mark.parametrize("seed", [0, 1])
def test_the_metal_is_found_and_its_streaks_reduced(seed: int) -> None:
    shares = _phantom(6.0)
    projections, truth = _scan(shares, seed)
    result = nmar(projections, GEOMETRY, GRID)
    true_metal = shares["CoCr"] >= 0.5
    dice = 2 * (result.metal & true_metal).sum() / (result.metal.sum() + true_metal.sum())
    assert dice >= 0.8  # 1.5 mm voxels on a 6 mm rod: its rim is the uncertain voxel
    free = fdk_reconstruct(_scan(_phantom(0.0), seed)[0], GEOMETRY, GRID).volume.data
    metal_share = np.asarray(shares["CoCr"])
    before = _rmse_outside(result.uncorrected.data, truth, metal_share)
    after = _rmse_outside(result.volume.data, truth, metal_share)
    reference = _rmse_outside(free, truth, metal_share)
    # the streaks (the error beyond the metal-free scan's) shrink to a third or less
    assert after - reference <= (before - reference) / 3
    assert np.array_equal(result.volume.data[result.metal], result.uncorrected.data[result.metal])


def test_metal_whose_shadow_cannot_be_interpolated_is_refused() -> None:
    projections, _ = _scan(_phantom(17.0), 0)
    with pytest.raises(
        ValueError, match=r"covers \d+ % of the object's in view \d+.*too much metal"
    ):
        nmar(projections, GEOMETRY, GRID)


def test_a_scan_without_metal_is_refused() -> None:
    projections, _ = _scan(_phantom(0.0), 0)
    with pytest.raises(ValueError, match="no metal in the volume"):
        nmar(projections, GEOMETRY, GRID)


def test_cbct_recon_mar_writes_the_volume_and_the_metal(tmp_path) -> None:
    projections, _ = _scan(_phantom(6.0), 0)
    write_projections(tmp_path / "p.mha", projections, 2.0)
    write_rtk_geometry(tmp_path / "g.xml", GEOMETRY)
    out = tmp_path / "volume.mha"
    argv = [
        "recon",
        "--projections",
        str(tmp_path / "p.mha"),
        "--geometry",
        str(tmp_path / "g.xml"),
    ]
    argv += ["--out", str(out), "--size", "64", "64", "24", "--spacing-mm", "1.5", "--mar"]
    result = CliRunner().invoke(app, argv, terminal_width=400)
    assert result.exit_code == 0, result.output
    assert "MAR: metal:" in result.output
    metal = read_volume(tmp_path / "volume_metal.mha")
    assert metal.data.sum() * 1.5**3 == pytest.approx(2 * np.pi * 36 * 36, rel=0.25)
    again = CliRunner().invoke(app, argv, terminal_width=400)
    assert again.exit_code != 0 and "exists" in again.output

"""CT numbers and attenuation: water's attenuation by energy, and HU <-> 1/mm.

``HU = 1000 (mu - mu_water) / mu_water``, so ``mu = mu_water (1 + HU / 1000)`` at the scan's
effective energy: a CT from another scanner comes in HU, and every stage that renders
radiographs needs linear attenuation (1/mm). The effective energy sets only the scale (the
bone-to-water contrast is the one the CT measured at its own spectrum); registration's
similarity (NCC) ignores a scale, the DRR's absolute line integrals do not.
"""

from __future__ import annotations

import math

import numpy as np

from recon.volume import Volume

WATER_MASS_ATTENUATION_CM2_G: dict[float, float] = {
    20.0: 0.8096,
    30.0: 0.3756,
    40.0: 0.2683,
    50.0: 0.2269,
    60.0: 0.2059,
    80.0: 0.1837,
    100.0: 0.1707,
    150.0: 0.1505,
}
"""Mass attenuation of liquid water, cm^2/g (coherent scattering included), by photon energy
(keV): NIST X-ray mass attenuation coefficients (Hubbell & Seltzer, NISTIR 5632)."""

DEFAULT_EFFECTIVE_ENERGY_KEV = 70.0
"""Effective energy assumed for CT numbers when none is given: a knee CT or CBCT at 100-120
kVp behind the leg's filtration (and the phantom's, sim.phantoms.knee)."""


ENERGY_RANGE_KEV = (
    float(min(WATER_MASS_ATTENUATION_CM2_G)),
    float(max(WATER_MASS_ATTENUATION_CM2_G)),
)
"""The effective energies the water table covers, keV (lowest, highest)."""


def mu_water_per_mm(effective_energy_kev: float) -> float:
    """Linear attenuation of water (density 1 g/cm^3) at an effective energy, 1/mm: the NIST
    table interpolated log-log, 20-150 keV."""
    energies = np.array(list(WATER_MASS_ATTENUATION_CM2_G))
    energy = float(effective_energy_kev)
    low, high = ENERGY_RANGE_KEV
    if not (math.isfinite(energy) and low <= energy <= high):
        raise ValueError(
            f"effective energy {effective_energy_kev!r} keV is outside the water table's "
            f"{low:g}-{high:g} keV"
        )
    values = np.log(list(WATER_MASS_ATTENUATION_CM2_G.values()))
    mass = math.exp(float(np.interp(math.log(energy), np.log(energies), values)))
    return mass / 10.0  # cm^2/g x 1 g/cm^3 -> 1/cm -> 1/mm


def hu_to_mu(volume: Volume, effective_energy_kev: float) -> Volume:
    """A volume in HU as linear attenuation (1/mm) at ``effective_energy_kev``; CT numbers
    below -1000 (scanners pad with -1024 or -3024) are air, 0 /mm."""
    if volume.unit != "HU":
        raise ValueError(f"hu_to_mu needs a volume in HU, got unit {volume.unit!r}")
    mu_water = mu_water_per_mm(effective_energy_kev)
    data = np.maximum(mu_water * (1.0 + np.asarray(volume.data, np.float64) / 1000.0), 0.0)
    return Volume(data.astype(np.float32), volume.grid, "1/mm")


def mu_to_hu(mu_per_mm: np.ndarray, mu_water: float) -> np.ndarray:
    """CT numbers (float64) of attenuation values (1/mm) given water's attenuation (1/mm)."""
    return 1000.0 * (np.asarray(mu_per_mm, dtype=np.float64) - mu_water) / mu_water

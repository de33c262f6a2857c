"""An X-ray tube's spectrum, and the attenuation of a knee's materials over it: what a
polychromatic projection needs (beam hardening, metal's photon starvation).

- The spectrum is Kramers' bremsstrahlung of a tungsten anode, ``N(E) ~ (kVp - E) / E``
  photons per keV, behind the tube's inherent filtration (2.5 mm of aluminium, the IEC
  minimum at these voltages) and any added filter; tungsten's characteristic K lines
  (58-69 keV, a few % of the output) are left out.
- The panel integrates energy (a CsI scintillator): a photon's signal is proportional to its
  energy, so each energy bin weighs ``N(E) E``.
- Mass attenuation (coherent scattering included) comes from Elam's tables through
  ``xraydb``, mixed by each material's composition by weight.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import xraydb

INHERENT_AL_MM = 2.5
"""The tube's inherent filtration, mm of aluminium."""
LOWEST_KEV = 15.0
"""The spectrum's lowest energy bin, keV (below it the filtration leaves nothing)."""


@dataclass(frozen=True)
class Composition:
    """A material: its elements by weight and its density.

    Attributes:
        name: The material's name.
        weights: Element symbol -> fraction by weight (they are normalised to 1).
        density_g_cm3: Density, g/cm^3.
    """

    name: str
    weights: dict[str, float]
    density_g_cm3: float

    def mu_per_mm(self, energies_kev: np.ndarray) -> np.ndarray:
        """Linear attenuation at each energy (keV), 1/mm."""
        energies_ev = 1000.0 * np.atleast_1d(np.asarray(energies_kev, dtype=np.float64))
        total = sum(self.weights.values())
        mass = sum(
            w / total * np.asarray(xraydb.mu_elam(element, energies_ev))
            for element, w in self.weights.items()
        )
        return mass * self.density_g_cm3 / 10.0


WATER = {"H": 0.1119, "O": 0.8881}
"""Water by weight."""
CORTICAL_BONE = {
    "H": 0.034,
    "C": 0.155,
    "N": 0.042,
    "O": 0.435,
    "Na": 0.001,
    "Mg": 0.002,
    "P": 0.103,
    "S": 0.003,
    "Ca": 0.225,
}
"""Cortical bone by weight (ICRU Report 44)."""

COMPOSITIONS = {
    c.name: c
    for c in (
        Composition("water", WATER, 1.0),
        Composition("cortical_bone", CORTICAL_BONE, 1.92),
        Composition(
            "cancellous_bone",  # a quarter cortical bone, the rest marrow (water), by weight
            {
                e: 0.25 * CORTICAL_BONE.get(e, 0.0) + 0.75 * WATER.get(e, 0.0)
                for e in (*CORTICAL_BONE, "H")
            },
            1.18,
        ),
        Composition("CoCr", {"Co": 0.65, "Cr": 0.28, "Mo": 0.06, "Ni": 0.01}, 8.3),
        Composition("Ti6Al4V", {"Ti": 0.90, "Al": 0.06, "V": 0.04}, 4.43),
        Composition("UHMWPE", {"C": 0.8563, "H": 0.1437}, 0.94),
        Composition("aluminium", {"Al": 1.0}, 2.70),
        Composition("copper", {"Cu": 1.0}, 8.96),
    )
}
"""The materials of a knee replacement and its surroundings: water (soft tissue), cortical and
cancellous bone, CoCrMo (ASTM F75), Ti-6Al-4V, the insert's polyethylene, and the tube's
filters."""


@dataclass(frozen=True)
class Spectrum:
    """A polychromatic beam as an energy-integrating panel weighs it.

    Attributes:
        energies_kev: Bin centres, keV (E,).
        weights: Each bin's share of the unattenuated signal (photons x energy), summing to 1.
    """

    energies_kev: np.ndarray
    weights: np.ndarray

    def hardened(self, material: str, thickness_mm: float) -> Spectrum:
        """The spectrum behind ``thickness_mm`` of ``material``."""
        mu = COMPOSITIONS[material].mu_per_mm(self.energies_kev)
        weights = self.weights * np.exp(-mu * thickness_mm)
        return Spectrum(self.energies_kev, weights / weights.sum())

    def mean_mu_per_mm(self, material: str) -> float:
        """The material's attenuation averaged over the spectrum (its value in a
        reconstruction of this beam, to first order), 1/mm."""
        return float(self.weights @ COMPOSITIONS[material].mu_per_mm(self.energies_kev))

    def effective_energy_kev(self) -> float:
        """The energy at which water attenuates as it does averaged over the spectrum, keV."""
        target = self.mean_mu_per_mm("water")
        grid = np.linspace(self.energies_kev[0], self.energies_kev[-1], 2000)
        mu = COMPOSITIONS["water"].mu_per_mm(grid)
        return float(grid[np.argmin(np.abs(mu - target))])

    def transmission(self, mu_by_bin: np.ndarray, lengths: np.ndarray) -> np.ndarray:
        """The signal's transmitted share along rays through several materials.

        Args:
            mu_by_bin: Each material's attenuation per energy bin (M, E), 1/mm.
            lengths: Each material's path length per ray (M, ...), mm.

        Returns:
            ``sum_E w_E exp(-sum_m mu_m(E) L_m)`` per ray, float64 of ``lengths.shape[1:]``.
        """
        flat = lengths.reshape(len(lengths), -1)
        out = np.zeros(flat.shape[1])
        for k, w in enumerate(self.weights):
            out += w * np.exp(-(mu_by_bin[:, k] @ flat))
        return out.reshape(lengths.shape[1:])


def tube_spectrum(
    kvp: float, *, bin_kev: float = 2.0, added_filter: tuple[str, float] | None = None
) -> Spectrum:
    """A tungsten tube's spectrum at ``kvp`` behind its inherent and any added filtration.

    Args:
        kvp: The tube voltage, kV (40-150).
        bin_kev: The energy bins' width, keV.
        added_filter: (material, mm) added to the inherent 2.5 mm of aluminium.

    Returns:
        The spectrum as the panel weighs it.
    """
    if not 40.0 <= kvp <= 150.0:
        raise ValueError(f"tube voltage {kvp} kV outside the spectrum model's 40-150 kV")
    if not 0.1 <= bin_kev <= 10.0:
        raise ValueError(f"bin_kev {bin_kev} keV outside 0.1-10 keV")
    energies = np.arange(LOWEST_KEV + 0.5 * bin_kev, kvp, bin_kev)
    photons = (kvp - energies) / energies
    spectrum = Spectrum(energies, photons * energies / np.sum(photons * energies))
    spectrum = spectrum.hardened("aluminium", INHERENT_AL_MM)
    if added_filter is not None:
        spectrum = spectrum.hardened(*added_filter)
    return spectrum

"""A static scan from any scanner as linear attenuation (1/mm), with where its unit came from.

Volumes come as NIfTI, MetaImage or a DICOM CT series, in HU or 1/mm. The unit is read from
the file where it says (our files' note, a CT series' modality), from the caller where it does
not (``cbct register --unit``), and otherwise from the values when they leave no doubt: CT
numbers span hundreds (air -1000, bone +1000), attenuation a fraction of one per mm. A unit the
values contradict, or values that could be either, are refused before any work, the option
named. HU is converted once, here, at a stated effective energy (recon.attenuation).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from recon.attenuation import DEFAULT_EFFECTIVE_ENERGY_KEV, hu_to_mu, mu_water_per_mm
from recon.dicom import read_dicom_series
from recon.io import VOLUME_SUFFIXES, read_volume, volume_unit_note
from recon.volume import Volume

StaticUnit = Literal["HU", "1/mm"]

HU_SPAN = 50.0
"""Values spanning at least this (0.1-99.9 percentiles), or reaching -200 and below, are CT
numbers: no tissue attenuates 50 per mm, and attenuation is never negative beyond noise."""
MU_RANGE = (-0.5, 10.0)
"""Values within this range (1/mm; lead attenuates about 4 per mm at 70 keV, noise dips below
zero) are attenuation; CT numbers only fit in it for a near-uniform object of about water's."""

OPTION = "--unit hu or --unit 1/mm"


@dataclass(frozen=True)
class StaticSource:
    """Where a static volume came from and how it became attenuation.

    Attributes:
        path: the file or DICOM folder.
        unit: the unit its values were in.
        unit_from: "file" (its note or modality), "option" (the caller) or "values".
        effective_energy_kev: the energy HU were converted at (None for 1/mm).
        mu_water_per_mm: water's attenuation there, 1/mm (None for 1/mm).
        value_range: 0.1 and 99.9 percentiles of the values as read.
    """

    path: str
    unit: StaticUnit
    unit_from: str
    effective_energy_kev: float | None
    mu_water_per_mm: float | None
    value_range: tuple[float, float]

    def summary(self) -> dict:
        """A JSON-ready record for outputs (registration.json)."""
        return asdict(self)


def read_attenuation(
    path: str | Path,
    unit: StaticUnit | None = None,
    effective_energy_kev: float = DEFAULT_EFFECTIVE_ENERGY_KEV,
) -> tuple[Volume, StaticSource]:
    """A static scan (NIfTI, MetaImage, or a folder holding one DICOM CT series) in 1/mm.

    Args:
        path: the file or folder.
        unit: "HU" or "1/mm" for files that do not state it (must agree when they do).
        effective_energy_kev: the energy HU are converted at (recon.attenuation).

    Raises:
        ValueError: a unit the file or its values contradict, values that could be either
            unit without one given, a label volume, an energy outside the water table.
        FileNotFoundError, OSError: unreadable inputs (recon.io, recon.dicom).
    """
    path = Path(path)
    mu_water_per_mm(effective_energy_kev)  # the energy is checked before anything is read
    if unit is not None and unit not in ("HU", "1/mm"):
        raise ValueError(f"unit must be 'HU' or '1/mm', got {unit!r}")
    if path.is_dir():
        volume, stated = read_dicom_series(path), "HU"
    else:
        if not path.exists():
            raise FileNotFoundError(f"{path}: no such file or folder")
        if not path.name.lower().endswith(VOLUME_SUFFIXES):
            raise ValueError(
                f"{path}: a static scan is a {', '.join(VOLUME_SUFFIXES)} file or a folder "
                "holding one DICOM CT series"
            )
        stated = volume_unit_note(path)
        if stated == "label":
            raise ValueError(f"{path}: a label volume, not a scan (it states unit=label)")
        # read as stated, else as given, else provisionally as HU (the values decide below)
        volume = read_volume(path, None if stated is not None else unit or "HU")
    low, high = (float(x) for x in np.percentile(volume.data, (0.1, 99.9)))
    looks = _unit_by_values(low, high)
    if stated is not None:
        if unit is not None and unit != stated:
            raise ValueError(f"{path}: the file states unit {stated!r}, but {unit!r} was given")
        chosen, source = stated, "file"
    elif unit is not None:
        if looks is not None and looks != unit:
            raise ValueError(
                f"{path}: values {low:g}..{high:g} (0.1-99.9 percentiles) are "
                f"{_words(looks)}, not {_words(unit)}: the unit given contradicts them "
                f"({OPTION})"
            )
        chosen, source = unit, "option"
    elif looks is not None:
        chosen, source = looks, "values"
    else:
        raise ValueError(
            f"{path}: the file does not state its unit and its values {low:g}..{high:g} (0.1-99.9 "
            f"percentiles) could be CT numbers or attenuation: give its unit ({OPTION})"
        )
    if chosen == "1/mm":
        volume = Volume(volume.data, volume.grid, "1/mm")
        return volume, StaticSource(str(path), "1/mm", source, None, None, (low, high))
    hu = Volume(volume.data, volume.grid, "HU")
    water = mu_water_per_mm(effective_energy_kev)
    converted = hu_to_mu(hu, effective_energy_kev)
    info = StaticSource(str(path), "HU", source, float(effective_energy_kev), water, (low, high))
    return converted, info


def _unit_by_values(low: float, high: float) -> StaticUnit | None:
    """The unit values spanning ``low..high`` can only be in, or None when they could be
    either (:data:`HU_SPAN`, :data:`MU_RANGE`)."""
    if high - low >= HU_SPAN or low <= -200.0:
        return "HU"
    if MU_RANGE[0] <= low and high <= MU_RANGE[1]:
        return "1/mm"
    return None


def _words(unit: StaticUnit) -> str:
    return "CT numbers (HU)" if unit == "HU" else "attenuation in 1/mm"

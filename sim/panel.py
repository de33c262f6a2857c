"""The simulated flat panel's sensor: how photons become raw counts on a real panel.

A real panel's read-out is not the photons it saw. Each pixel adds its own offset (dark
current), converts with its own gain, some pixels are dead or hot and some lines are dead, the
analog chain adds read-out noise, and a fraction of each frame's charge stays trapped and shows
in the next frame (lag). :class:`PanelSensor` applies all of these, seeded by the panel's serial
number and read-out size (the same panel in the same mode always has the same defects), and
returns unsigned 16-bit counts (ADU) as a GigE Vision panel delivers them in Mono16.
:mod:`scanner.corrections` undoes them from dark and flood frames.
"""

from __future__ import annotations

import zlib

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

ADU_MAX = 65535
"""Full scale of a Mono16 read-out, ADU."""


class SimPanelSpec(BaseModel):
    """The simulated panel's imperfections (``panel`` in configs/backends/sim.yaml)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    serial: str = Field("SIM-PANEL-0001", min_length=1, description="the panel's serial number")
    flood_adu: float = Field(
        40000.0, gt=0.0, le=60000.0, description="an unattenuated pixel at the reference technique"
    )
    offset_adu: float = Field(1000.0, ge=0.0, le=10000.0, description="mean dark offset, ADU")
    offset_spread_adu: float = Field(60.0, ge=0.0, description="per-pixel offset spread (SD), ADU")
    gain_spread: float = Field(0.05, ge=0.0, le=0.3, description="per-pixel relative gain SD")
    gain_ramp: float = Field(
        0.08, ge=0.0, le=0.5, description="smooth gain change from the panel's top to its bottom"
    )
    read_noise_adu: float = Field(2.0, ge=0.0, description="read-out noise SD, ADU")
    dead_pixels: float = Field(0.002, ge=0.0, le=0.05, description="fraction of dead pixels")
    hot_pixels: float = Field(0.001, ge=0.0, le=0.05, description="fraction of hot pixels")
    dead_columns: int = Field(2, ge=0, le=16, description="columns that read only their offset")
    weak_rows: int = Field(1, ge=0, le=16, description="rows at a third of their gain")
    lag: float = Field(0.03, ge=0.0, le=0.2, description="fraction of a frame's signal in the next")


class PanelSensor:
    """One panel in one read-out mode: photons in, raw Mono16 counts out.

    Args:
        spec: the imperfections.
        rows: read-out rows.
        cols: read-out columns.
        adu_per_photon: the mode's conversion gain, ADU per detected photon.
        seed: the panel's defect seed (with its serial number and size).
    """

    def __init__(
        self, spec: SimPanelSpec, rows: int, cols: int, adu_per_photon: float, seed: int = 0
    ) -> None:
        self.spec, self.rows, self.cols = spec, rows, cols
        self.adu_per_photon = adu_per_photon
        rng = np.random.default_rng([seed, zlib.crc32(f"{spec.serial} {rows}x{cols}".encode())])
        shape = (rows, cols)
        self.offset = spec.offset_adu + rng.normal(0.0, spec.offset_spread_adu, shape)
        ramp = 1.0 + spec.gain_ramp * (np.linspace(-0.5, 0.5, rows)[:, None])
        self.gain = ramp * (1.0 + rng.normal(0.0, spec.gain_spread, shape))
        self.dead = rng.random(shape) < spec.dead_pixels
        self.hot = rng.random(shape) < spec.hot_pixels
        self.dead[:, rng.choice(cols, spec.dead_columns, replace=False)] = True
        self.gain[rng.choice(rows, spec.weak_rows, replace=False), :] /= 3.0
        self.gain[self.dead] = 0.0
        self.offset[self.hot] += rng.uniform(5000.0, 20000.0, int(self.hot.sum()))
        self._trapped = np.zeros(shape)

    def read(self, photons: np.ndarray | None, rng: np.random.Generator) -> np.ndarray:
        """The raw frame of one integration window, uint16 ADU.

        Args:
            photons: detected photons per pixel in the window (rows, cols); None for a dark
                frame (no pulse in the window).
            rng: the read-out noise's generator.
        """
        signal = np.zeros((self.rows, self.cols)) if photons is None else np.asarray(photons)
        released = self._trapped
        lag = self.spec.lag
        self._trapped = lag * signal
        charge = (1.0 - lag) * signal + released
        adu = self.offset + self.gain * self.adu_per_photon * charge
        adu += rng.normal(0.0, self.spec.read_noise_adu, adu.shape)
        hot_noise = rng.normal(0.0, 30.0 * self.spec.read_noise_adu + 1.0, adu.shape)
        adu[self.hot] += hot_noise[self.hot]
        return np.clip(np.rint(adu), 0, ADU_MAX).astype(np.uint16)

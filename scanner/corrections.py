"""Flat-panel corrections: offset, gain, defect and lag maps from dark and flood frames.

A panel's raw counts are ``offset + gain * charge``, per pixel, where the charge of a frame is
most of its own signal and a fraction (``lag``) of the frame before it. Some pixels and lines
are dead, weak or hot. :func:`derive_maps` measures all of this from frames taken with the
X-ray off (darks) and with nothing in the beam at a stated technique (floods), then darks
again (the first of them holds the charge the floods left behind: the lag):

- offset: the mean dark, ADU;
- gain: mean flood minus offset, ADU (what an unattenuated pixel reads at the calibration
  technique);
- defects: pixels whose dark mean or noise, or whose gain, is an outlier of the panel's
  (robust statistics: median and MAD), and lines where most pixels are;
- lag: the first dark after the floods over the floods' signal, the panel's median.

:class:`Corrector` turns each raw frame into line integrals ``-ln(I / I0)``: offset removed,
lag removed recursively (each frame minus the charge its predecessor left), gain divided out,
defects filled from their good neighbours, and ``I0`` taken from the part of the frame that
sees air (the tube's output drifts from pulse to pulse), or from the flood scaled by the
technique when too little of the frame sees air (or what looks like air is more than
:data:`AIR_DRIFT` away from the flood's output: a frame the leg fills is attenuated everywhere).

Maps are stored as one ``.npz`` per panel and mode, ``<serial>/<mode>.npz`` under a folder,
with the serial number, mode, technique, frame count and date; :func:`find_maps` refuses maps
of another panel, another mode or older than a limit.
"""

from __future__ import annotations

import datetime as dt
import json
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

DEFECT_SIGMAS = 8.0
"""A pixel whose dark mean, dark noise or gain lies this many robust standard deviations from
the panel's median is defective."""
GAIN_LIMITS = (0.5, 1.5)
"""A pixel whose gain is outside this fraction of the median gain is defective."""
LINE_DEFECT_FRACTION = 0.5
"""A row or column with this fraction of its pixels defective is defective as a whole."""
AIR_FRACTION = 0.05
"""The least fraction of a frame that must see air for its ``I0`` to be measured in it."""
AIR_LEVEL = 0.9
"""Pixels within this fraction of the frame's brightest (99th percentile) are taken as air."""
AIR_DRIFT = 1.2
"""The largest factor between the tube's output in a frame and the flood's (scaled by mAs) that
is taken for drift: a brighter or darker 'air' is attenuated, or the technique is wrong."""


class MapsError(ValueError):
    """Detector maps missing, of another panel or mode, too old, or unreadable."""


@dataclass(frozen=True)
class PanelMaps:
    """Offset, gain, defect and lag maps of one panel in one read-out mode.

    Attributes:
        serial: the panel's serial number.
        mode: the read-out mode (e.g. ``"256x256 Mono16"``).
        offset: mean dark counts per pixel, ADU, (rows, cols).
        gain: mean flood minus offset per pixel, ADU, (rows, cols).
        defects: defective pixels, bool (rows, cols).
        lag: fraction of a frame's signal read in the next frame.
        kv: the floods' tube voltage, kVp.
        mas: the floods' tube load per frame, mAs.
        frames: dark and flood frames averaged, each.
        made: when the maps were made (UTC, ISO 8601).
        noise_adu: the darks' median temporal noise, ADU.
    """

    serial: str
    mode: str
    offset: np.ndarray
    gain: np.ndarray
    defects: np.ndarray
    lag: float
    kv: float
    mas: float
    frames: int
    made: str
    noise_adu: float

    def summary(self) -> dict:
        """What a user checks: panel, mode, technique, defects and lag."""
        rows = np.flatnonzero(self.defects.all(axis=1))
        cols = np.flatnonzero(self.defects.all(axis=0))
        return {
            "serial": self.serial,
            "mode": self.mode,
            "made": self.made,
            "kv": self.kv,
            "mas": self.mas,
            "frames": self.frames,
            "offset_adu_median": float(np.median(self.offset)),
            "flood_adu_median": float(np.median(self.gain[~self.defects])),
            "dark_noise_adu": self.noise_adu,
            "defective_pixels": int(self.defects.sum()),
            "defective_rows": rows.tolist(),
            "defective_cols": cols.tolist(),
            "lag": self.lag,
        }

    def save(self, folder: Path) -> Path:
        """Write ``folder/<serial>/<mode>.npz`` (a new file: refuses to overwrite); returns it."""
        path = maps_path(folder, self.serial, self.mode)
        if path.exists():
            raise MapsError(f"{path} exists: detector maps are never overwritten")
        path.parent.mkdir(parents=True, exist_ok=True)
        meta = {k: getattr(self, k) for k in ("serial", "mode", "lag", "kv", "mas", "frames")}
        meta |= {"made": self.made, "noise_adu": self.noise_adu}
        partial = path.with_suffix(".partial.npz")
        np.savez_compressed(
            partial,
            offset=self.offset.astype(np.float32),
            gain=self.gain.astype(np.float32),
            defects=self.defects,
            meta=np.array(json.dumps(meta)),
        )
        partial.rename(path)
        return path

    @classmethod
    def load(cls, path: Path) -> PanelMaps:
        """Read maps written by :meth:`save`; raises MapsError naming the file."""
        try:
            with np.load(path) as data:
                meta = json.loads(str(data["meta"]))
                arrays = {k: data[k] for k in ("offset", "gain", "defects")}
            return cls(**meta, **arrays)
        except (OSError, KeyError, TypeError, ValueError) as err:
            raise MapsError(f"{path}: not readable detector maps ({err})") from err


def maps_path(folder: Path, serial: str, mode: str) -> Path:
    """Where the maps of panel ``serial`` in ``mode`` live under ``folder``."""

    def safe(name: str) -> str:
        return re.sub(r"[^A-Za-z0-9._-]+", "_", name)

    return Path(folder) / safe(serial) / f"{safe(mode)}.npz"


def find_maps(
    folder: Path, serial: str, mode: str, max_age_days: float, now: dt.datetime | None = None
) -> PanelMaps:
    """The newest usable maps of panel ``serial`` in ``mode``; raises MapsError naming the
    folder, what is there and the limit when there are none, or they are too old."""
    path = maps_path(folder, serial, mode)
    if not path.is_file():
        others = sorted(str(p.relative_to(folder)) for p in Path(folder).glob("*/*.npz"))
        raise MapsError(
            f"no detector maps for panel {serial!r} in mode {mode!r} in {folder} (it holds "
            f"{others or 'none'}): run `cbct detector-calibrate` for this panel and mode"
        )
    maps = PanelMaps.load(path)
    if (maps.serial, maps.mode) != (serial, mode):
        raise MapsError(f"{path} holds maps of {maps.serial!r} in {maps.mode!r}")
    now = now or dt.datetime.now(dt.UTC)
    age = (now - dt.datetime.fromisoformat(maps.made)).total_seconds() / 86400.0
    if age > max_age_days:
        raise MapsError(
            f"{path}: detector maps are {age:.1f} days old, the limit is {max_age_days:g} days: "
            "run `cbct detector-calibrate` again"
        )
    return maps


def _robust_outliers(values: np.ndarray, sigmas: float) -> np.ndarray:
    """Pixels more than ``sigmas`` robust SDs (1.4826 MAD) from the median."""
    median = np.median(values)
    spread = 1.4826 * np.median(np.abs(values - median))
    return np.abs(values - median) > sigmas * max(spread, 1e-6)


def derive_maps(
    darks: np.ndarray,
    floods: np.ndarray,
    after: np.ndarray,
    *,
    serial: str,
    mode: str,
    kv: float,
    mas: float,
    made: dt.datetime | None = None,
) -> PanelMaps:
    """Offset, gain, defect and lag maps from raw frames.

    Args:
        darks: dark frames (X-ray off), (n, rows, cols), ADU; the first is left out (it may
            hold lag of frames before the calibration).
        floods: flood frames (nothing in the beam), (n, rows, cols), ADU; the first is left out
            (it lacks the lag of the floods before it).
        after: dark frames taken right after the floods, (m >= 1, rows, cols), ADU.
        serial: the panel's serial number.
        mode: the read-out mode.
        kv: the floods' tube voltage, kVp.
        mas: the floods' tube load per frame, mAs.
        made: when (UTC; default now).

    Returns:
        The maps.
    """
    if len(darks) < 3 or len(floods) < 3 or len(after) < 1:
        raise MapsError(
            f"detector calibration needs >= 3 darks, >= 3 floods and 1 dark after them; got "
            f"{len(darks)}, {len(floods)}, {len(after)}"
        )
    darks = np.asarray(darks, dtype=np.float64)[1:]
    floods = np.asarray(floods, dtype=np.float64)[1:]
    offset = darks.mean(axis=0)
    noise = darks.std(axis=0, ddof=1)
    gain = floods.mean(axis=0) - offset
    median_gain = np.median(gain)
    if median_gain <= 20.0 * max(np.median(noise), 0.5):
        raise MapsError(
            f"the floods read {median_gain:.0f} ADU above the darks: no X-rays reached the panel"
        )
    relative = gain / median_gain
    defects = (
        _robust_outliers(offset, DEFECT_SIGMAS)
        | (noise > DEFECT_SIGMAS * max(np.median(noise), 0.5))
        | (relative < GAIN_LIMITS[0])
        | (relative > GAIN_LIMITS[1])
    )
    defects[defects.mean(axis=1) >= LINE_DEFECT_FRACTION, :] = True
    defects[:, defects.mean(axis=0) >= LINE_DEFECT_FRACTION] = True
    left = np.asarray(after[0], dtype=np.float64) - offset
    lag = float(np.median(left[~defects] / gain[~defects]))
    made = made or dt.datetime.now(dt.UTC)
    return PanelMaps(
        serial=serial,
        mode=mode,
        offset=offset,
        gain=np.where(defects, median_gain, gain),
        defects=defects,
        lag=float(np.clip(lag, 0.0, 0.5)),
        kv=float(kv),
        mas=float(mas),
        frames=len(floods) + 1,
        made=made.isoformat(),
        noise_adu=float(np.median(noise)),
    )


CUBIC = np.array([-1.0, 4.0, 4.0, -1.0]) / 6.0
"""Weights of the two good neighbours each side that fill a pixel (exact for a cubic)."""


class DefectFill:
    """Fills a panel's defective pixels from good neighbours, planned once per defect map.

    A pixel whose two neighbours on each side along its row (along its column when its row
    is defective as a whole) are good takes their cubic interpolation, ``(-a + 4 b + 4 c -
    d) / 6``: exact for a cubic, so that a dead column leaves no ring of the projection's
    curvature. The others take the mean of their good 3 x 3 neighbours (edges replicated),
    widened to 7 x 7 where that has none. Pixels filled in a step are good for the next. The
    plan (which pixels, from which, with what weights) depends on the map alone, so a frame
    costs a gather over the defects, not filters over the whole panel.

    Args:
        defects: the defect map, bool (rows, cols).
    """

    def __init__(self, defects: np.ndarray) -> None:
        rows, cols = defects.shape
        bad = np.asarray(defects, dtype=bool).copy()
        self._steps: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        lines = bad.all(axis=1)
        r, c = np.nonzero(bad & ~lines[:, None])
        self._cubic(bad, r, c, (r[:, None], c[:, None] + np.array([-2, -1, 1, 2])))
        r, c = np.nonzero(bad & lines[:, None])
        self._cubic(bad, r, c, (r[:, None] + np.array([-2, -1, 1, 2]), c[:, None]))
        for half in (1, 3):
            r, c = np.nonzero(bad)
            if not len(r):
                break
            dr, dc = (a.ravel() for a in np.mgrid[-half : half + 1, -half : half + 1])
            nr = np.clip(r[:, None] + dr, 0, rows - 1)  # edges replicated
            nc = np.clip(c[:, None] + dc, 0, cols - 1)
            weight = (~bad[nr, nc]).astype(np.float64)
            total = weight.sum(axis=1)
            fill = total > 0
            weight = weight[fill] / total[fill, None]
            targets = np.ravel_multi_index((r[fill], c[fill]), bad.shape)
            sources = np.ravel_multi_index((nr[fill], nc[fill]), bad.shape)
            self._steps.append((targets, sources, weight))
            bad[r[fill], c[fill]] = False

    def _cubic(self, bad: np.ndarray, r: np.ndarray, c: np.ndarray, near: tuple) -> None:
        """Plan the cubic step of the pixels (r, c) whose four neighbours ``near`` are inside
        the panel and good; they are good from then on."""
        nr, nc = near
        nr, nc = np.broadcast_arrays(nr, nc)
        inside = (nr >= 0) & (nr < bad.shape[0]) & (nc >= 0) & (nc < bad.shape[1])
        usable = inside.all(axis=1)
        usable[usable] = ~bad[nr[usable], nc[usable]].any(axis=1)
        targets = np.ravel_multi_index((r[usable], c[usable]), bad.shape)
        sources = np.ravel_multi_index((nr[usable], nc[usable]), bad.shape)
        self._steps.append((targets, sources, np.broadcast_to(CUBIC, sources.shape)))
        bad[r[usable], c[usable]] = False

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """``image`` with its defective pixels filled; in place, returned."""
        flat = image.reshape(-1)
        for targets, sources, weights in self._steps:
            flat[targets] = (flat[sources] * weights).sum(axis=1)
        return image


class Corrector:
    """Raw frames of one scan in, line integrals out (stateful: lag carries frame to frame).

    Args:
        maps: the panel's maps (of the scan's panel and mode).
    """

    def __init__(self, maps: PanelMaps) -> None:
        self.maps = maps
        self._fill = DefectFill(maps.defects)
        self._previous: np.ndarray | None = None  # the last frame's signal, ADU
        self.air_views = 0
        self.flood_views = 0

    def signal(self, raw: np.ndarray) -> np.ndarray:
        """The frame's own signal, ADU: offset and its predecessor's lag removed, float64."""
        m = self.maps
        charge = np.asarray(raw, dtype=np.float64) - m.offset
        if self._previous is not None:
            charge -= m.lag * self._previous
        signal = charge / (1.0 - m.lag)
        self._previous = signal
        return signal

    def line_integrals(self, raw: np.ndarray, kv: float, mas: float) -> np.ndarray:
        """``-ln(I / I0)`` of one raw frame exposed at ``kv`` / ``mas``, float32 (rows, cols)."""
        m = self.maps
        ratio = self.signal(raw) / m.gain  # I / I_flood
        self._fill(ratio)
        expected = mas / m.mas  # the flood's output, scaled by the tube load
        scale = self.i0_ratio(ratio, expected)
        if scale is None:
            scale = expected
            self.flood_views += 1
        else:
            self.air_views += 1
        ratio /= scale
        np.maximum(ratio, 1e-6, out=ratio)
        return (-np.log(ratio)).astype(np.float32)

    @staticmethod
    def i0_ratio(ratio: np.ndarray, expected: float) -> float | None:
        """The frame's unattenuated level relative to the flood, from the pixels that see air;
        None when fewer than :data:`AIR_FRACTION` of them do, or when their level is further
        than :data:`AIR_DRIFT` from ``expected`` (then the brightest part of the frame is
        attenuated, not air)."""
        top = np.percentile(ratio, 99.0)
        air = ratio >= AIR_LEVEL * top
        if air.mean() < AIR_FRACTION or top <= 0:
            return None
        level = float(np.median(ratio[air]))
        if abs(np.log(level / expected)) > np.log(AIR_DRIFT):
            return None
        return level

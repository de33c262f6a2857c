"""Benchmark: the flat panel over GigE Vision, and the panel's corrections in a reconstruction.

GigE Vision (scanner.gige.GigEPanel against sim.gige_panel, Aravis's fake GigE Vision camera
serving our sensor's frames, on a loopback address):

- ``gige_frames``, ``gige_lost``, ``gige_fps``: ``--frames`` frames of 512 x 512 Mono16 in
  software-trigger mode, one arm -> read_frame per frame as fast as they come, the sensor
  answering at once with one of 8 seeded random images in turn; ``gige_frames`` counts the
  frames read and equal to the image the sensor gave, ``gige_lost`` the frames the driver
  found lost (block id gaps), ``gige_errors`` the reads that raised;
  ``gige_frame_period_ms`` (median) and ``gige_frame_period_p99_ms`` the arm-to-arm period;
  ``gige_stream_*`` Aravis's stream counters (missing and resent packets, underruns).
- ``gige_camera_gone_to_error_s``: an acquisition paced at ``--gone-fps`` frames/s whose arm
  and read wait at most two frame periods (``gige_frame_timeout_s``; one warm-up frame read
  when it connects: the first after the stream starts is late), the fake panel SIGKILLed
  at a random moment (``--gone-trials`` times, a new panel each); the time from the kill to
  the driver's error (DeviceError or DeviceTimeout from arm or read_frame), the worst trial
  (``..._median_s`` the median, ``..._each_s`` each), ``gige_camera_gone_frame_periods`` the
  worst in frame periods; ``gige_camera_gone_bound_s`` three frame periods;
  ``gige_camera_gone_false_alarms`` the trials whose acquisition failed before the kill (each
  run again: a frame later than two periods with the camera alive). A scan's SAFE
  follows the error at once (X-ray off, arms stopped: tests/scanner/test_gige_scan.py).

Corrections (the demo knee, ``--views`` views of ``--panel`` pixels square, FDK at
``--voxel-mm``, reconstructed four times from the same noise-free projections):

- ``rmse_ideal_panel``: photons with Poisson and read-out noise, ``-ln(I / I0)`` with the
  exact I0 (sim.scan.add_noise);
- ``rmse_corrected``: the same photons read out by the simulated real panel (sim.panel:
  offset, gain, defects, lag, 2 ADU read noise, 16-bit), corrected with maps derived from
  16 darks and 16 floods of it (scanner.corrections);
- ``rmse_uncorrected``: that panel's raw counts over their air level, nothing corrected;
- RMSE against the phantom inside the leg, 1/mm, as the demo's recon stage measures it;
- ``ring_amplitude_*``: rings about the rotation axis in units of the image's noise SD. In
  the soft tissue 3 voxels from any other tissue, the reconstruction minus the noise-free
  one's, averaged over 1-voxel-wide rings about the axis (all slices), minus that radial
  profile smoothed (Gaussian, sigma 3 rings); the RMS over the rings, divided by the SD of
  the ideal panel's voxels about the noise-free reconstruction in the same region
  (``noise_sd_per_mm``).

Prints one JSON object. Usage: ``python bench/detector.py [--frames 360] [--interface
127.0.0.3] [--views 180 --panel 256 --voxel-mm 0.8] [--skip-gige | --skip-recon]`` (the
interface must be an address of an interface: ``ip addr add 127.0.0.3/32 dev lo``; see
.ci/run).
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from collections import Counter
from pathlib import Path

import numpy as np
from scipy import ndimage

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from scanner.gige import GigEPanel  # noqa: E402
from scanner.hardware import DeviceError  # noqa: E402
from sim.gige_panel import aravis_missing, fake_panel_with_sensor  # noqa: E402

ROWS, COLS = 512, 512
SERIAL = "BENCH-PANEL"
WINDOW_MS = 10.0
PIXEL_PITCH_MM = 0.278


class _Images:
    """The sensor: seeded random images in turn, and which one each request got."""

    def __init__(self, seed: int, n: int = 8) -> None:
        rng = np.random.default_rng(seed)
        self.images = rng.integers(0, 0xFFFF, (n, ROWS, COLS), dtype=np.uint16, endpoint=True)
        self.given = 0

    def __call__(self, _window_s: float) -> np.ndarray:
        image = self.images[self.given % len(self.images)]
        self.given += 1
        return image


def _log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def gige_frames(frames: int, interface: str, timeout_s: float, seed: int = 0) -> dict:
    """Frames through the driver in software-trigger mode (see the module docstring)."""
    sensor = _Images(seed)
    with fake_panel_with_sensor(interface, SERIAL, ROWS, COLS, sensor):
        panel = GigEPanel(interface, ROWS, COLS, PIXEL_PITCH_MM, window_ms=WINDOW_MS)
        panel.connect(5.0)
        good, errors, arms = 0, Counter(), []
        try:
            start = time.perf_counter()
            for _ in range(frames):
                arms.append(time.perf_counter())
                given = sensor.given
                try:
                    panel.arm(timeout_s)
                    counts = panel.read_frame(timeout_s).counts
                except DeviceError as error:
                    errors[type(error).__name__] += 1
                    _log(f"gige_frames: {error}")
                    continue
                good += np.array_equal(counts, sensor.images[given % len(sensor.images)])
            wall_s = time.perf_counter() - start
            stats = panel.statistics()
        finally:
            panel.close()
    period_ms = np.diff(arms) * 1e3
    return {
        "gige_frames": good,
        "gige_frames_requested": frames,
        "gige_lost": stats["frames_lost"],
        "gige_errors": dict(errors),
        "gige_fps": round(frames / wall_s, 1),
        "gige_frame_period_ms": round(float(np.median(period_ms)), 2),
        "gige_frame_period_p99_ms": round(float(np.percentile(period_ms, 99)), 2),
        "gige_window_ms": WINDOW_MS,
        **{
            f"gige_{key}": value
            for key, value in stats.items()
            if key.startswith("stream_") and key != "stream_completed_buffers"
        },
    }


def _one_kill(interface: str, period_s: float, delay_s: float) -> tuple[float, str]:
    """Kill the fake ``delay_s`` into an acquisition paced at ``period_s`` whose arm and read
    wait at most two periods: (time from the kill to the error, its kind); negative when the
    error came before the kill (a false alarm)."""
    sensor = _Images(0)
    with fake_panel_with_sensor(interface, SERIAL, ROWS, COLS, sensor) as (fake, _):
        panel = GigEPanel(
            interface, ROWS, COLS, PIXEL_PITCH_MM, window_ms=WINDOW_MS,
            frame_timeout_s=2 * period_s, warmup_frames=1,
        )  # fmt: skip
        panel.connect(5.0)
        killer = threading.Timer(delay_s, fake.kill)
        killer.start()
        try:
            next_arm = time.monotonic()
            while True:
                time.sleep(max(next_arm - time.monotonic(), 0.0))
                next_arm += period_s
                try:
                    panel.arm(5.0)
                    panel.read_frame(5.0)
                except DeviceError as error:
                    failed_at = time.monotonic()
                    kind = (
                        f"{type(error).__name__} in {'arm' if 'Trigger' in str(error) else 'read'}"
                    )
                    if "incomplete" in str(error):
                        kind += " (incomplete)"
                    break
        finally:
            killer.join()
            panel.close()
    assert fake.killed_at is not None
    return failed_at - fake.killed_at, kind


def gige_camera_gone(interface: str, fps: float, trials: int, seed: int = 0) -> dict:
    """The camera killed mid-acquisition ``trials`` times (see the module docstring)."""
    rng = np.random.default_rng(seed)
    period_s = 1.0 / fps
    results, false_alarms = [], []
    while len(results) < trials:
        elapsed_s, kind = _one_kill(interface, period_s, float(rng.uniform(0.3, 0.6)))
        if elapsed_s < 0:  # the acquisition failed before the kill: a false alarm, again
            false_alarms.append(kind)
            _log(f"camera gone: a false alarm {-elapsed_s:.3f} s before the kill ({kind})")
            continue
        results.append((elapsed_s, kind))
    elapsed = [r[0] for r in results]
    return {
        "gige_camera_gone_to_error_s": round(max(elapsed), 3),
        "gige_camera_gone_to_error_median_s": round(float(np.median(elapsed)), 3),
        "gige_camera_gone_to_error_each_s": [round(e, 3) for e in elapsed],
        "gige_camera_gone_frame_periods": round(max(elapsed) / period_s, 2),
        "gige_camera_gone_bound_s": round(3 * period_s, 3),
        "gige_camera_gone_errors": dict(Counter(r[1] for r in results)),
        "gige_camera_gone_trials": trials,
        "gige_camera_gone_false_alarms": len(false_alarms),
        "gige_camera_gone_fps": fps,
        "gige_frame_timeout_s": round(2 * period_s, 4),
    }


CALIBRATION_FRAMES = 16
"""Darks and floods of the corrected panel's maps, each (as the demo's detector stage)."""
SOFT_TISSUE = 1
"""The phantom's soft-tissue label (registration.labels.LABELS)."""


def panel_recon(views: int, panel: int, voxel_mm: float, seed: int = 0) -> dict:
    """The demo knee through an ideal, a corrected and an uncorrected panel (see the module
    docstring)."""
    from recon.config import load_config, load_protocol
    from recon.fdk import fdk_reconstruct
    from scanner.corrections import Corrector, derive_maps
    from sim.detector import REFERENCE_TECHNIQUE
    from sim.panel import PanelSensor, SimPanelSpec
    from sim.phantoms.knee import KneePhantomSpec, rasterize_knee
    from sim.scan import add_noise, photons_per_pixel, simulate_knee_scan
    from study.stages import recon_grid

    base = load_protocol(ROOT / "configs" / "protocols" / "demo_knee.yaml")
    pitch = base.detector.width_mm / panel
    detector = base.detector.model_copy(
        update={"rows": panel, "cols": panel, "pixel_pitch_mm": pitch}
    )
    orbit = base.orbit.model_copy(update={"views": views})
    protocol = base.model_copy(update={"detector": detector, "orbit": orbit})
    knee = load_config(ROOT / "configs" / "phantoms" / "knee.yaml", KneePhantomSpec)
    _log(f"recon: projecting the knee, {views} views of {panel}^2")
    clean = simulate_knee_scan(protocol, knee, voxel_mm=0.5, noise=False, seed=seed)
    e, sdd = protocol.exposure, protocol.orbit.sdd_mm
    photons = photons_per_pixel(e, detector, sdd)
    rng = np.random.default_rng(seed)
    ideal = add_noise(clean.projections, photons, rng)[1]

    spec = SimPanelSpec()
    reference = photons_per_pixel(REFERENCE_TECHNIQUE, detector, sdd)
    sensor = PanelSensor(spec, panel, panel, spec.flood_adu / reference, seed)
    flood = np.full((panel, panel), photons)
    darks = np.stack([sensor.read(None, rng) for _ in range(CALIBRATION_FRAMES)])
    floods = np.stack([sensor.read(rng.poisson(flood), rng) for _ in range(CALIBRATION_FRAMES)])
    after = np.stack([sensor.read(None, rng) for _ in range(2)])
    maps = derive_maps(
        darks, floods, after, serial=spec.serial, mode="bench", kv=e.tube_kv, mas=e.mas
    )
    corrector = Corrector(maps)
    corrected, uncorrected = np.empty_like(ideal), np.empty_like(ideal)
    for k, p in enumerate(clean.projections):
        raw = sensor.read(rng.poisson(photons * np.exp(-p.astype(np.float64))), rng)
        corrected[k] = corrector.line_integrals(raw, e.tube_kv, e.mas)
        counts = np.maximum(raw.astype(np.float64), 1.0)
        level = np.median(counts)
        air = Corrector.i0_ratio(counts / level, 1.0) or 1.0
        uncorrected[k] = -np.log(counts / (air * level))

    grid = recon_grid(protocol, voxel_mm)
    labels, truth = rasterize_knee(knee, grid, supersample=2)
    stacks = {
        "noise_free": clean.projections,
        "ideal_panel": ideal,
        "corrected": corrected,
        "uncorrected": uncorrected,
    }
    volumes = {}
    for name, stack in stacks.items():
        _log(f"recon: FDK of the {name.replace('_', ' ')} projections")
        volumes[name] = fdk_reconstruct(stack, clean.geometry, grid)
    mask = volumes["noise_free"].mask
    inside = (labels > 0) & mask
    uniform = ndimage.binary_erosion((labels == SOFT_TISSUE) & mask, iterations=3)
    reference_volume = volumes["noise_free"].volume.data
    noise = float(np.std((volumes["ideal_panel"].volume.data - reference_volume)[uniform]))
    result: dict = {"noise_sd_per_mm": noise}
    axis = protocol.orbit.isocenter_mm[:2]
    for name in ("ideal_panel", "corrected", "uncorrected"):
        data = volumes[name].volume.data
        result[f"rmse_{name}"] = float(np.sqrt(np.mean((data - truth)[inside] ** 2)))
        rings = ring_amplitude(data - reference_volume, uniform, grid, axis)
        result[f"ring_amplitude_{name}"] = rings / noise
    result["rmse_corrected_over_ideal"] = result["rmse_corrected"] / result["rmse_ideal_panel"]
    result["recon"] = {
        "views": views,
        "pixels": panel,
        "voxel_mm": voxel_mm,
        "calibration_frames": CALIBRATION_FRAMES,
        "defective_pixels_found": int(maps.defects.sum()),
        "defective_pixels_planted": int((sensor.dead | sensor.hot).sum()),
        "lag_measured": maps.lag,
        "lag_true": spec.lag,
        "views_with_i0_from_air": corrector.air_views,
    }
    return result


def ring_amplitude(difference: np.ndarray, uniform: np.ndarray, grid, axis_xy) -> float:
    """The rings of ``difference`` about the rotation axis (the vertical through ``axis_xy``,
    mm) in ``uniform``: its radial profile (means over 1-voxel-wide rings, all slices) minus
    that profile smoothed (Gaussian, sigma 3 rings), RMS over the rings, in its units."""
    x, y, _ = grid.axes_mm()  # the volume is indexed [z, y, x]
    dx, dy = x - axis_xy[0], y - axis_xy[1]
    r = np.broadcast_to(np.hypot(dx[None, None, :], dy[None, :, None]), difference.shape)
    bins = np.rint(r[uniform] / grid.spacing_mm[0]).astype(int)
    count = np.bincount(bins)
    profile = (np.bincount(bins, difference[uniform]) / np.maximum(count, 1))[count >= 50]
    smooth = ndimage.gaussian_filter1d(profile, 3.0, mode="nearest")
    return float(np.sqrt(np.mean((profile - smooth) ** 2)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=360, help="frames of the throughput run")
    parser.add_argument("--interface", default="127.0.0.3", help="the fake panel's address")
    parser.add_argument("--frame-timeout-s", type=float, default=0.5, help="throughput timeout")
    parser.add_argument("--gone-trials", type=int, default=5, help="camera-gone kills")
    parser.add_argument("--gone-fps", type=float, default=30.0, help="camera-gone pacing")
    parser.add_argument("--views", type=int, default=180, help="views of the reconstruction")
    parser.add_argument("--panel", type=int, default=256, help="panel pixels (square)")
    parser.add_argument("--voxel-mm", type=float, default=0.8, help="reconstruction voxel, mm")
    parser.add_argument("--skip-gige", action="store_true", help="no GigE Vision figures")
    parser.add_argument("--skip-recon", action="store_true", help="no reconstruction figures")
    args = parser.parse_args()
    result: dict = {}
    missing = None if args.skip_gige else aravis_missing()
    if missing is not None:
        result["gige_skipped"] = missing
    elif not args.skip_gige:
        _log(f"GigE: {args.frames} frames of {COLS}x{ROWS} Mono16 at {args.interface}")
        result.update(gige_frames(args.frames, args.interface, args.frame_timeout_s))
        _log(f"GigE: the camera killed mid-acquisition, {args.gone_trials} times")
        result.update(gige_camera_gone(args.interface, args.gone_fps, args.gone_trials))
    if not args.skip_recon:
        result.update(panel_recon(args.views, args.panel, args.voxel_mm))
    print(json.dumps(result))


if __name__ == "__main__":
    main()

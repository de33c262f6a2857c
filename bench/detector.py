"""Benchmark: the flat-panel driver over GigE Vision (scanner.gige.GigEPanel) against the fake
panel (sim.gige_panel: Aravis's fake GigE Vision camera serving our sensor's frames) on a
loopback address.

- ``gige_frames``, ``gige_lost``, ``gige_fps``: ``--frames`` frames of 512 x 512 Mono16 in
  software-trigger mode, one arm -> read_frame per frame, the sensor answering at once with
  one of 8 seeded random images in turn; ``gige_frames`` counts the frames read and equal to
  the image the sensor gave, ``gige_lost`` the frames the driver found lost (block id gaps),
  ``gige_errors`` the reads that raised; ``gige_frame_period_ms`` (median) and
  ``gige_frame_period_p99_ms`` the arm-to-arm period; ``gige_stream_*`` Aravis's stream
  counters (missing and resent packets, underruns).
- ``gige_camera_gone_to_error_s``: the fake panel SIGKILLed at a random moment of such an
  acquisition (``--gone-trials`` times, a new panel each), the time from the kill to the
  driver's error (DeviceError or DeviceTimeout from arm or read_frame), the worst of the
  trials (``..._median_s`` the median, ``..._each_s`` every trial's);
  ``gige_camera_gone_bound_s`` the driver's bound, the frame timeout
  (``gige_frame_timeout_s``, the arm and read timeout) plus one frame period (the median
  above); ``gige_camera_gone_errors`` how the trials failed.

Prints one JSON object. Usage: ``python bench/detector.py [--frames 360] [--interface
127.0.0.3]`` (the interface must be an address of an interface: ``ip addr add 127.0.0.3/32 dev
lo``; see .ci/run).
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


def _one_kill(interface: str, timeout_s: float, delay_s: float) -> tuple[float, str, float]:
    """Kill the fake ``delay_s`` into an acquisition: (time to the error, its kind, the median
    frame period before the kill)."""
    sensor = _Images(0)
    with fake_panel_with_sensor(interface, SERIAL, ROWS, COLS, sensor) as (fake, _):
        panel = GigEPanel(interface, ROWS, COLS, PIXEL_PITCH_MM, window_ms=WINDOW_MS)
        panel.connect(5.0)
        killer = threading.Timer(delay_s, fake.kill)
        arms: list[float] = []
        killer.start()
        try:
            while True:
                arms.append(time.monotonic())
                try:
                    panel.arm(timeout_s)
                    panel.read_frame(timeout_s)
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
    before = [t for t in arms if t < fake.killed_at]
    period_s = float(np.median(np.diff(before))) if len(before) > 1 else float("nan")
    return failed_at - fake.killed_at, kind, period_s


def gige_camera_gone(interface: str, timeout_s: float, trials: int, seed: int = 0) -> dict:
    """The camera killed mid-acquisition ``trials`` times (see the module docstring)."""
    rng = np.random.default_rng(seed)
    results = [_one_kill(interface, timeout_s, float(rng.uniform(0.3, 0.6))) for _ in range(trials)]
    elapsed = [r[0] for r in results]
    period_s = float(np.nanmedian([r[2] for r in results]))
    return {
        "gige_camera_gone_to_error_s": round(max(elapsed), 3),
        "gige_camera_gone_to_error_median_s": round(float(np.median(elapsed)), 3),
        "gige_camera_gone_to_error_each_s": [round(e, 3) for e in elapsed],
        "gige_camera_gone_bound_s": round(timeout_s + period_s, 3),
        "gige_camera_gone_errors": dict(Counter(r[1] for r in results)),
        "gige_camera_gone_trials": trials,
        "gige_frame_timeout_s": timeout_s,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=360, help="frames of the throughput run")
    parser.add_argument("--interface", default="127.0.0.3", help="the fake panel's address")
    parser.add_argument("--frame-timeout-s", type=float, default=0.5, help="arm/read timeout")
    parser.add_argument("--gone-trials", type=int, default=5, help="camera-gone kills")
    args = parser.parse_args()
    missing = aravis_missing()
    if missing is not None:
        print(json.dumps({"gige_skipped": missing}))
        return
    result: dict = {}
    _log(f"GigE: {args.frames} frames of {COLS}x{ROWS} Mono16 at {args.interface}")
    result.update(gige_frames(args.frames, args.interface, args.frame_timeout_s))
    _log(f"GigE: the camera killed mid-acquisition, {args.gone_trials} times")
    result.update(gige_camera_gone(args.interface, args.frame_timeout_s, args.gone_trials))
    print(json.dumps(result))


if __name__ == "__main__":
    main()

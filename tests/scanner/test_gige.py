"""scanner.gige.GigEPanel against sim.gige_panel: Aravis's fake GigE Vision camera (the real
GVCP/GVSP stack over loopback) serving the frames our sensor gives it.

The fakes of this module serve on 127.0.0.2 (one camera per address; other modules use other
addresses, so that they run in parallel). The camera-gone bounds are in test_gige_realtime.py.
"""

from __future__ import annotations

import re
import sys
import time

import numpy as np
import pytest

from scanner.gige import GigEPanel, block_id_after, block_id_step
from scanner.hardware import DeviceError, DeviceTimeout
from sim.gige_panel import (
    FakePanelAddressError,
    aravis_missing,
    fake_panel_with_sensor,
    start_fake_panel,
)
from sim.gige_panel import test_pattern as panel_test_pattern

ADDRESS = "127.0.0.2"
SERIAL = "SIM-PANEL-0002"
ROWS, COLS = 512, 512
WINDOW_MS = 5.0
TIMEOUT_S = 2.0

needs_aravis = pytest.mark.skipif(aravis_missing() is not None, reason=str(aravis_missing()))


class Sensor:
    """Seeded random counts, one image per request, kept for comparison."""

    def __init__(self, seed: int = 0) -> None:
        self.rng = np.random.default_rng(seed)
        self.images: list[np.ndarray] = []
        self.windows_s: list[float] = []

    def __call__(self, window_s: float) -> np.ndarray:
        image = self.rng.integers(0, 0xFFFF, (ROWS, COLS), dtype=np.uint16, endpoint=True)
        self.images.append(image)
        self.windows_s.append(window_s)
        return image


def _skip_without_address(error: FakePanelAddressError) -> None:
    pytest.skip(f"{error} (see .ci/run)")


@pytest.fixture
def fake():
    """A fake panel on ADDRESS fed by a fresh :class:`Sensor`: (panel, sensor, server)."""
    sensor = Sensor()
    try:
        with fake_panel_with_sensor(ADDRESS, SERIAL, ROWS, COLS, sensor) as (panel, server):
            yield panel, sensor, server
    except FakePanelAddressError as error:
        _skip_without_address(error)


def _started(rows: int = ROWS, cols: int = COLS, **options):
    try:
        return start_fake_panel(ADDRESS, SERIAL, rows, cols, **options)
    except FakePanelAddressError as error:
        _skip_without_address(error)


def _panel(**options) -> GigEPanel:
    return GigEPanel(ADDRESS, ROWS, COLS, 0.278, window_ms=WINDOW_MS, **options)


def test_block_ids_wrap_from_65535_to_1() -> None:
    assert block_id_step(5, 6) == 1
    assert block_id_step(65535, 1) == 1
    assert block_id_step(65534, 2) == 3
    assert block_id_step(7, 7) == 0
    assert block_id_step(1, 65535) == -1
    assert block_id_step(0xFFFF, 0x10000) == 1  # extended (64-bit) ids do not wrap
    assert block_id_after(65535, 1) == 1
    assert block_id_after(65534, 3) == 2


def test_imports_and_refuses_without_aravis(monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "gi", None)
    panel = _panel()
    with pytest.raises(DeviceError, match=r"gir1\.2-aravis-0\.8.*python3-gi.*Makefile") as err:
        panel.connect(1.0)
    assert "ln -sfn /usr/lib/python3/dist-packages/gi" in str(err.value)
    panel.close()


@needs_aravis
def test_frames_carry_the_sensors_counts(fake) -> None:
    _, sensor, server = fake
    panel = _panel()
    panel.connect(TIMEOUT_S)
    try:
        assert (panel.serial, panel.mode) == (SERIAL, "512x512 Mono16")
        for i in range(20):
            panel.arm(TIMEOUT_S)
            frame = panel.read_frame(TIMEOUT_S)
            assert frame.counts.dtype == np.uint16 and frame.counts.flags.writeable
            np.testing.assert_array_equal(frame.counts, sensor.images[i])
        stats = panel.statistics()
    finally:
        panel.close()
    assert server.requests == 20 and not server.errors
    assert sensor.windows_s == pytest.approx([WINDOW_MS / 1e3] * 20)
    assert stats["frames"] == 20
    assert stats["frames_lost"] == stats["frames_late"] == stats["frames_incomplete"] == 0
    assert stats["stream_completed_buffers"] == 20 and stats["stream_underruns"] == 0


@needs_aravis
def test_without_a_sensor_the_panel_sends_its_test_pattern() -> None:
    with _started():
        panel = _panel()
        panel.connect(TIMEOUT_S)
        try:
            panel.arm(TIMEOUT_S)
            frame = panel.read_frame(TIMEOUT_S)
        finally:
            panel.close()
    expected = panel_test_pattern(ROWS, COLS, panel.stats.last_block_id)
    np.testing.assert_array_equal(frame.counts, expected)


@needs_aravis
@pytest.mark.parametrize(
    ("rows", "cols", "message"),
    [
        (256, COLS, r"Height: the camera reads out 256 rows .* configured with 512"),
        (ROWS, 1024, r"Width: the camera reads out 1024 columns .* configured with 512"),
    ],
    ids=["rows", "cols"],
)
def test_a_panel_of_another_size_is_refused(rows, cols, message) -> None:
    with _started(rows, cols):
        panel = _panel()
        with pytest.raises(DeviceError, match=message):
            panel.connect(TIMEOUT_S)
        panel.close()


@needs_aravis
def test_a_camera_without_mono16_is_refused() -> None:
    with _started(pixel_formats=("Mono8", "RGB8")):
        panel = _panel()
        with pytest.raises(DeviceError, match=r"PixelFormat: no Mono16; .* offers Mono8, RGB8"):
            panel.connect(TIMEOUT_S)
        panel.close()


@needs_aravis
def test_a_skipped_block_id_is_a_lost_frame() -> None:
    with _started(skip_block_id_after=3):
        panel = _panel()
        panel.connect(TIMEOUT_S)
        try:
            ids = []
            for _ in range(3):
                panel.arm(TIMEOUT_S)
                panel.read_frame(TIMEOUT_S)
                ids.append(panel.stats.last_block_id)
            panel.arm(TIMEOUT_S)
            with pytest.raises(DeviceError, match=r"1 frame\(s\) lost") as err:
                panel.read_frame(TIMEOUT_S)
            named = re.search(r"block id (\d+) follows (\d+), expected (\d+)", str(err.value))
            assert named is not None, err.value
            expected = block_id_after(ids[-1], 1)
            assert [int(x) for x in named.groups()] == [
                block_id_after(ids[-1], 2),
                ids[-1],
                expected,
            ]
            panel.arm(TIMEOUT_S)  # the panel goes on from the new id
            panel.read_frame(TIMEOUT_S)
            assert panel.frames_lost == 1
            assert panel.statistics()["stream_missing_frames"] == 1
        finally:
            panel.close()


@needs_aravis
def test_frames_missing_packets_are_refused() -> None:
    # Aravis's fake drops 5 % of the stream packets and does not resend: (nearly) every frame
    # of ~190 packets is incomplete
    with _started(gvsp_lost_ratio=0.05):
        panel = _panel()
        panel.connect(TIMEOUT_S)
        try:
            panel.arm(TIMEOUT_S)
            with pytest.raises(DeviceError, match=r"incomplete: status"):
                panel.read_frame(TIMEOUT_S)
            assert panel.stats.frames_incomplete == 1 and panel.stats.frames == 0
        finally:
            panel.close()


@needs_aravis
def test_a_late_frame_is_drained_and_the_next_window_reads_its_own(fake) -> None:
    _, sensor, _ = fake
    panel = _panel()
    panel.connect(TIMEOUT_S)
    try:
        panel.arm(TIMEOUT_S)
        with pytest.raises(DeviceTimeout):
            panel.read_frame(0.0)  # gives up before the fake (1 ms trigger poll) can answer
        time.sleep(0.2)  # the frame arrives late
        panel.arm(TIMEOUT_S)
        frame = panel.read_frame(TIMEOUT_S)
        np.testing.assert_array_equal(frame.counts, sensor.images[1])
        assert (panel.stats.timeouts, panel.stats.frames_late, panel.frames_lost) == (1, 1, 0)
    finally:
        panel.close()


@needs_aravis
def test_hardware_trigger_waits_for_the_line() -> None:
    # Aravis's fake has no trigger line: with TriggerSource Line0 it sends nothing (in free run
    # or software trigger it would)
    with _started():
        panel = _panel(trigger="line0")
        panel.connect(TIMEOUT_S)
        try:
            panel.arm(TIMEOUT_S)
            with pytest.raises(DeviceTimeout, match=r"no frame within 0\.3 s"):
                panel.read_frame(0.3)
        finally:
            panel.close()


@needs_aravis
def test_close_twice_then_connect_again(fake) -> None:
    _, sensor, _ = fake
    panel = _panel()
    panel.connect(TIMEOUT_S)
    panel.close()
    panel.close()
    with pytest.raises(DeviceError, match="not connected"):
        panel.arm(TIMEOUT_S)
    panel.connect(TIMEOUT_S)  # the camera's control was released
    try:
        panel.arm(TIMEOUT_S)
        np.testing.assert_array_equal(panel.read_frame(TIMEOUT_S).counts, sensor.images[0])
    finally:
        panel.close()
        panel.close()

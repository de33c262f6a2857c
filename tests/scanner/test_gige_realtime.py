"""scanner.gige.GigEPanel when the camera dies: the fake panel (sim.gige_panel) SIGKILLed
during an acquisition, and the wall-clock time until the driver raises. Marked ``realtime``
(tests/conftest.py: REALTIME). The fakes of this module serve on 127.0.0.3."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from scanner.gige import CLOSE_TIMEOUT_S, GigEPanel
from scanner.hardware import DeviceError, DeviceTimeout
from sim.gige_panel import FakePanelAddressError, aravis_missing, fake_panel_with_sensor

pytestmark = pytest.mark.skipif(aravis_missing() is not None, reason=str(aravis_missing()))

ADDRESS = "127.0.0.3"
SERIAL = "SIM-PANEL-0003"
ROWS, COLS = 512, 512
TIMEOUT_S = 0.3
"""The arm and read timeouts of these tests (the frame timeout), s."""
SLACK_S = 0.15
"""Scheduling allowance on a loaded two-core machine, s."""


@pytest.fixture
def fake():
    image = np.random.default_rng(0).integers(0, 4096, (ROWS, COLS), dtype=np.uint16)
    try:
        with fake_panel_with_sensor(ADDRESS, SERIAL, ROWS, COLS, lambda _w: image) as (panel, _):
            yield panel
    except FakePanelAddressError as error:
        pytest.skip(f"{error} (see .ci/run)")


def test_camera_killed_mid_acquisition_fails_the_next_call_within_its_timeout(fake) -> None:
    """Bound: the kill lands in a read (no frame comes: DeviceTimeout after the read's
    timeout; a frame cut off mid-transfer: DeviceError, incomplete, after Aravis's frame
    retention of 0.1 s) or in an arm (TriggerSoftware unanswered: DeviceTimeout after the arm's
    timeout), or between them with one frame still in flight: the frame timeout plus one frame
    period. Close then waits at most for its AcquisitionStop (CLOSE_TIMEOUT_S)."""
    panel = GigEPanel(ADDRESS, ROWS, COLS, 0.278, window_ms=5.0)
    panel.connect(2.0)
    starts = []
    killer = threading.Timer(0.4, fake.kill)
    killer.start()
    try:
        with pytest.raises(DeviceError) as err:
            for _ in range(10_000):
                starts.append(time.monotonic())
                panel.arm(TIMEOUT_S)
                panel.read_frame(TIMEOUT_S)
        failed_at = time.monotonic()
    finally:
        killer.join()
        closing = time.monotonic()
        panel.close()
        close_s = time.monotonic() - closing
    assert fake.killed_at is not None and len(starts) > 10
    period_s = float(np.median(np.diff([t for t in starts if t < fake.killed_at])))
    bound_s = TIMEOUT_S + period_s + SLACK_S
    elapsed_s = failed_at - fake.killed_at
    assert 0 < elapsed_s <= bound_s, (elapsed_s, bound_s, err.value)
    assert close_s <= CLOSE_TIMEOUT_S + SLACK_S


def test_arm_after_the_camera_died_raises_within_its_timeout(fake) -> None:
    """Aravis retries an unanswered GVCP command 5 x 500 ms; arm gives up at its timeout and
    the panel is gone from then on."""
    panel = GigEPanel(ADDRESS, ROWS, COLS, 0.278, window_ms=5.0)
    panel.connect(2.0)
    try:
        panel.arm(TIMEOUT_S)
        panel.read_frame(TIMEOUT_S)
        fake.kill()
        start = time.monotonic()
        with pytest.raises(DeviceTimeout, match="TriggerSoftware: no answer within"):
            panel.arm(TIMEOUT_S)
        assert time.monotonic() - start <= TIMEOUT_S + SLACK_S
        start = time.monotonic()
        with pytest.raises(DeviceError, match="the camera is gone"):
            panel.read_frame(TIMEOUT_S)
        assert time.monotonic() - start < 0.05
        start = time.monotonic()
    finally:
        panel.close()
    assert time.monotonic() - start < 0.05  # close does not wait for a camera known gone

"""URArm against the protocol-level fake UR controller (sim.ur_controller), through the real
ur-rtde 1.6.2: one fake process per host address, as ur-rtde connects to fixed ports."""

from __future__ import annotations

import signal
import socket
import time

import numpy as np
import pytest

pytest.importorskip("rtde_control")
pytest.importorskip("rtde_receive")

from scanner.hardware import Arm, DeviceError, DeviceTimeout, ProtectiveStop
from scanner.ur import URArm
from sim.ur_controller import FakeURController

pytestmark = pytest.mark.timeout(60)

SOURCE_HOST, DETECTOR_HOST, PSTOP_HOST, SILENT_HOST, NOBODY_HOST = (
    "127.0.0.2",
    "127.0.0.3",
    "127.0.0.4",
    "127.0.0.5",
    "127.0.0.9",
)
SOURCE_HOME = np.array([12.5, -95.0, 100.0, -85.0, -90.0, 30.0])
DETECTOR_HOME = np.array([-170.0, -80.0, 95.5, -105.0, 90.0, -45.25])
JOINTS = (
    "shoulder_pan",
    "shoulder_lift",
    "elbow",
    "wrist_1",
    "wrist_2",
    "wrist_3",
)


@pytest.fixture(scope="module")
def fakes():
    """The source-arm and detector-arm controllers, as two processes."""
    with (
        FakeURController(SOURCE_HOST, SOURCE_HOME, name="source_arm") as source,
        FakeURController(DETECTOR_HOST, DETECTOR_HOME, name="detector_arm") as detector,
    ):
        yield {SOURCE_HOST: source, DETECTOR_HOST: detector}


def make_arm(name: str, host: str, **kwargs) -> URArm:
    return URArm(name, host, JOINTS, move_speed_deg_s=60.0, move_accel_deg_s2=240.0, **kwargs)


SETTLE_S = 0.016
"""Time from sending a servo set-point to reading the arm: the fake follows it with a 4 ms lag,
so a reading that has seen 2.8 ms of it (ln 2 time constants) is within half a step. The
rest, 13 ms, is the set-point's way in (ur-rtde's worker, RTDE's 2 ms cycle) and the
reading's way out: measured at most 10 ms with both cores busy (error at most 0.22 of a step
over 550 readings)."""


def smooth_ramp(s: float) -> float:
    """0 -> 1 with zero velocity and acceleration at both ends (quintic)."""
    return s**3 * (10.0 - 15.0 * s + 6.0 * s * s)


def test_connect_reads_home_and_closes_twice(fakes):
    arms = [make_arm("source_arm", SOURCE_HOST), make_arm("detector_arm", DETECTOR_HOST)]
    assert all(isinstance(arm, Arm) for arm in arms)
    for arm, home in zip(arms, (SOURCE_HOME, DETECTOR_HOME), strict=True):
        arm.connect(2.0)
        reading = arm.state(0.5)
        np.testing.assert_allclose(reading.q, home, rtol=0, atol=1e-6)
        assert not reading.protective_stop
        time.sleep(0.01)
        assert arm.state(0.5).t_s > reading.t_s
    for arm in arms:
        arm.close()
        arm.close()
        with pytest.raises(DeviceError, match="not connected"):
            arm.state(0.5)
    # everything was released: the registers are free for a new connection
    with make_arm("source_arm", SOURCE_HOST) as again:
        again.connect(2.0)
        np.testing.assert_allclose(again.state(0.5).q, SOURCE_HOME, rtol=0, atol=1e-6)


def test_move_servo_stop_two_arms(fakes):
    with (
        make_arm("source_arm", SOURCE_HOST) as source,
        make_arm("detector_arm", DETECTOR_HOST) as detector,
    ):
        arms = {source: SOURCE_HOME, detector: DETECTOR_HOME}
        for arm in arms:
            arm.connect(2.0)

        # point-to-point
        offset = np.array([8.0, -5.0, 6.0, 4.0, -7.0, 10.0])
        for arm, home in arms.items():
            arm.move_to(home + offset, timeout_s=5.0)
            np.testing.assert_allclose(arm.state(0.5).q, home + offset, rtol=0, atol=1e-3)

        # 1 s of a smooth ramp at 50 Hz, both arms streamed together
        amplitude = np.array([6.0, -4.0, 5.0, 3.0, -6.0, 8.0])
        dt = 0.02
        steps = 50
        start = {arm: home + offset for arm, home in arms.items()}
        previous = dict(start)
        t0 = time.monotonic()
        for k in range(1, steps + 1):
            for arm in arms:
                target = start[arm] + amplitude * smooth_ramp(k / steps)
                arm.servo(target, dt)
                previous[arm] = target
            sent = time.monotonic()
            # read at the next period, and never sooner than SETTLE_S after the set-point went
            # out (a loop that fell behind would read the arm the moment the set-point lands)
            time.sleep(max(0.0, t0 + k * dt - sent, SETTLE_S))
            for arm in arms:
                step = np.abs(amplitude).max() * (
                    smooth_ramp(k / steps) - smooth_ramp((k - 1) / steps)
                )
                error = np.abs(arm.state(0.5).q - previous[arm]).max()
                assert error <= 0.5 * step + 0.005, (k, error, step)
        time.sleep(0.1)
        for arm in arms:
            end = start[arm] + amplitude
            np.testing.assert_allclose(arm.state(0.5).q, end, rtol=0, atol=0.01)
            arm.stop()
            first = arm.state(0.5)
            time.sleep(0.05)
            second = arm.state(0.5)
            assert second.t_s >= first.t_s + 0.04
            np.testing.assert_allclose(second.q, first.q, rtol=0, atol=1e-9)

        # back home for whoever comes next
        for arm, home in arms.items():
            arm.move_to(home, timeout_s=5.0)
            np.testing.assert_allclose(arm.state(0.5).q, home, rtol=0, atol=1e-6)


def test_move_timeout_stops_the_arm(fakes):
    with URArm(
        "detector_arm", DETECTOR_HOST, JOINTS, move_speed_deg_s=5.0, move_accel_deg_s2=10.0
    ) as arm:
        arm.connect(2.0)
        goal = DETECTOR_HOME + np.array([30.0, 0, 0, 0, 0, 0])
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeout, match=r"detector_arm: move_to: moveJ .* 127\.0\.0\.3"):
            arm.move_to(goal, timeout_s=0.3)
        assert time.monotonic() - t0 < 1.0
        time.sleep(0.3)
        stopped = arm.state(0.5).q
        time.sleep(0.05)
        np.testing.assert_allclose(arm.state(0.5).q, stopped, rtol=0, atol=1e-9)
        assert 0.0 < stopped[0] - DETECTOR_HOME[0] < 30.0
        arm.move_to(DETECTOR_HOME, timeout_s=5.0)


def test_upper_range_registers(fakes):
    """ur-rtde's control script on registers 24-47 (offset injected into the script)."""
    with make_arm("source_arm", SOURCE_HOST, upper_range_registers=True) as arm:
        arm.connect(2.0)
        arm.move_to(SOURCE_HOME + 2.0, timeout_s=5.0)
        np.testing.assert_allclose(arm.state(0.5).q, SOURCE_HOME + 2.0, rtol=0, atol=1e-3)
        arm.move_to(SOURCE_HOME, timeout_s=5.0)


def test_second_client_is_refused_while_registers_are_in_use(fakes):
    with make_arm("detector_arm", DETECTOR_HOST) as first:
        first.connect(2.0)
        with pytest.raises(DeviceError, match=r"second: connect: .*127\.0\.0\.3.*in use"):
            make_arm("second", DETECTOR_HOST).connect(2.0)
        first.move_to(DETECTOR_HOME + 1.0, timeout_s=5.0)  # the first one still works
        first.move_to(DETECTOR_HOME, timeout_s=5.0)


def test_state_raises_when_the_stream_stalls(fakes):
    fake = fakes[DETECTOR_HOST]
    with make_arm("detector_arm", DETECTOR_HOST, freshness_s=0.05) as arm:
        arm.connect(2.0)
        arm.state(0.5)
        fake.process.send_signal(signal.SIGSTOP)
        try:
            time.sleep(0.15)  # longer than silence_s: reported at once, not after the timeout
            t0 = time.monotonic()
            with pytest.raises(DeviceTimeout, match=r"detector_arm: state: 127\.0\.0\.3 is silent"):
                arm.state(2.0)
            assert time.monotonic() - t0 < 0.05
        finally:
            fake.process.send_signal(signal.SIGCONT)
        time.sleep(0.05)
        np.testing.assert_allclose(arm.state(1.0).q, DETECTOR_HOME, rtol=0, atol=1e-6)


def test_protective_stop_after_servo_commands():
    home = np.array([0.0, -90.0, 90.0, -90.0, -90.0, 0.0])
    with (
        FakeURController(PSTOP_HOST, home, protective_stop_after_servo=10),
        make_arm("source_arm", PSTOP_HOST) as arm,
    ):
        arm.connect(2.0)
        sent = 0
        with pytest.raises(ProtectiveStop, match=r"source_arm: servo: 127\.0\.0\.4 .*protective"):
            for k in range(1, 40):
                arm.servo(home + 0.05 * k, 0.02)
                sent += 1
                time.sleep(0.02)
        assert 10 <= sent <= 12
        reading = arm.state(0.5)
        assert reading.protective_stop
        time.sleep(0.05)
        np.testing.assert_allclose(arm.state(0.5).q, reading.q, rtol=0, atol=1e-9)
        with pytest.raises(ProtectiveStop, match="move_to"):
            arm.move_to(home, timeout_s=2.0)
        arm.stop()  # already at standstill: nothing to do, no error
    assert not arm.connected  # closed by the with block


def test_connect_to_a_controller_that_answers_only_the_handshake_times_out():
    """RTDE answers the protocol-version request and nothing after it (the port probe passes):
    ur-rtde's constructor would wait forever holding the GIL; connect gives up at its timeout
    with the worker process that ran it killed."""
    home = np.array([0.0, -90.0, 90.0, -90.0, -90.0, 0.0])
    with FakeURController(SILENT_HOST, home, silent_after_handshake=True):
        arm = make_arm("source_arm", SILENT_HOST)
        t0 = time.monotonic()
        with pytest.raises(
            DeviceTimeout, match=r"source_arm: connect: .*127\.0\.0\.5 did not answer within"
        ):
            arm.connect(1.5)
        elapsed = time.monotonic() - t0
        assert 1.4 < elapsed < 1.5 + 0.2
        assert not arm.connected
        arm.close()


def test_a_controller_silent_mid_stream_is_reported_and_stop_returns():
    """The controller stops answering after 25 set-points: servo reports it within silence_s
    plus one set-point period, and stopping it gives up at stop_timeout_s instead of hanging."""
    home = np.array([0.0, -90.0, 90.0, -90.0, -90.0, 0.0])
    with (
        FakeURController(SILENT_HOST, home, silent_after_servo=25) as fake,
        make_arm("source_arm", SILENT_HOST, stop_timeout_s=0.5) as arm,
    ):
        arm.connect(2.0)
        with pytest.raises(DeviceTimeout, match=r"source_arm: servo: 127\.0\.0\.5 is silent"):
            for k in range(1, 200):
                arm.servo(home + 0.01 * k, 0.02)
                time.sleep(0.02)
        detected = time.monotonic()
        (silent_at,) = [t for name, t in fake.events() if name == "silent"]
        assert detected - silent_at < arm.silence_s + 0.02 + 0.05
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeout, match=r"source_arm: stop: 127\.0\.0\.5 did not answer"):
            arm.stop()
        assert time.monotonic() - t0 < 0.5 + 0.2
        assert not arm.connected


def test_connect_without_controller_times_out():
    arm = make_arm("source_arm", NOBODY_HOST)
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout, match=r"source_arm: connect: RTDE 127\.0\.0\.9:30004"):
        arm.connect(0.5)
    assert time.monotonic() - t0 < 0.7
    arm.close()  # never connected: nothing to do


def test_connect_to_a_silent_listener_times_out():
    """A port that accepts but never answers must not reach ur-rtde's constructors (which hold
    the GIL with no handshake timeout)."""
    with socket.socket() as listener:
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind((NOBODY_HOST, 30004))
        listener.listen(1)
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeout, match=r"127\.0\.0\.9:30004 accepted .* 0\.5 s"):
            make_arm("source_arm", NOBODY_HOST).connect(0.5)
        assert 0.45 < time.monotonic() - t0 < 0.8


def test_fake_answers_ur_rtde_default_receive_recipe(fakes):
    """ur-rtde's receive interface asks for every output it knows; the fake answers them all
    with their RTDE types, and time advances in real time."""
    import rtde_receive

    receive = rtde_receive.RTDEReceiveInterface(SOURCE_HOST)
    try:
        np.testing.assert_allclose(np.rad2deg(receive.getActualQ()), SOURCE_HOME, atol=1e-6)
        t0, wall0 = receive.getTimestamp(), time.monotonic()
        time.sleep(0.2)
        elapsed = receive.getTimestamp() - t0
        assert elapsed == pytest.approx(time.monotonic() - wall0, abs=0.03)
        assert receive.getRobotMode() == 7  # RUNNING
        assert receive.getSafetyMode() == 1  # NORMAL
        assert receive.getSafetyStatusBits() == 1
        assert not receive.isProtectiveStopped()
        assert receive.getJointMode() == [253] * 6
        pose = receive.getActualTCPPose()
        assert len(pose) == 6 and 0.2 < np.linalg.norm(pose[:3]) < 1.0  # UR5e reach, m
        assert receive.getPayloadCog() == [0.0, 0.0, 0.0]
        assert receive.getOutputIntRegister(12) == 0
    finally:
        del receive


def test_a_call_interrupted_by_ctrl_c_leaves_no_answer_for_the_next(fakes):
    """Ctrl-C (a real SIGINT) while a blocking moveJ waits for its answer: the answer that
    comes later is dropped, and the next call (the SAFE stop, here a read of the joints) gets
    its own, not the moveJ's (the soak saw 'too many values to unpack' in SAFE's stop)."""
    from scanner.ur_client import URClient

    client = URClient("source_arm", SOURCE_HOST)
    client.open(-1.0, ["actual_q"], False, 5.0)
    try:
        goal = np.deg2rad(SOURCE_HOME + 20.0).tolist()
        previous = signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.signal(signal.SIGALRM, lambda *_: signal.raise_signal(signal.SIGINT))
        signal.setitimer(signal.ITIMER_REAL, 0.1)
        try:
            with pytest.raises(KeyboardInterrupt):  # a 20 deg move at 10 deg/s takes 2 s
                client.call("control", "moveJ", goal, 0.17, 1.0, False, timeout_s=10, what="m")
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGINT, previous)
        q = client.call("receive", "getActualQ", timeout_s=10, what="read the joints")
        assert isinstance(q, list) and len(q) == 6  # the moveJ's answer was True
        client.call("control", "stopJ", 2.0, False, timeout_s=10, what="stop")
    finally:
        client.close(5.0)

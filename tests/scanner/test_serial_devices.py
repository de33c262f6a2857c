"""Serial drivers against the mock devices over real ptys: framing, generator, stage."""

from __future__ import annotations

import os
import select
import threading
import time
import tty
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager

import numpy as np
import pytest
import serial

from scanner.generator import SerialGenerator
from scanner.hardware import (
    Arm,
    DeviceError,
    DeviceTimeout,
    ProtectiveStop,
    Technique,
    XrayGenerator,
)
from scanner.serial_link import FrameError, SerialLink, decode_frame, encode_frame
from scanner.stage import SerialStage
from sim.generator import MockGenerator
from sim.pty_device import make_frame
from sim.stage import MockStage

TECHNIQUE = Technique(kv=110.0, ma=10.0, ms=20.0)

# -- framing and the link against a raw pty ----------------------------------------------------


@contextmanager
def raw_pty(respond: Callable[[bytes], bytes | None]) -> Iterator[str]:
    """A pty whose master answers each request line with ``respond(line)`` (None: silence)."""
    master, slave = os.openpty()
    tty.setraw(slave)
    stop = threading.Event()

    def serve() -> None:
        pending = b""
        while not stop.is_set():
            readable, _, _ = select.select([master], [], [], 0.02)
            if readable:
                pending += os.read(master, 1024)
            while b"\n" in pending:
                line, pending = pending.split(b"\n", 1)
                answer = respond(line + b"\n")
                if answer:
                    os.write(master, answer)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        yield os.ttyname(slave)
    finally:
        stop.set()
        thread.join()
        os.close(master)
        os.close(slave)


def test_frame_checksum_matches_spec_and_mock() -> None:
    assert encode_frame("ID?") == b"ID?*CC\r\n"
    assert encode_frame("KV 110.0") == b"KV 110.0*B1\r\n"
    for body in ("ID?", "OK EXP 110 10 20 3", "ERR KV RANGE kV 160 above limit 150"):
        assert make_frame(body) == encode_frame(body)  # independent implementations agree
        assert decode_frame(encode_frame(body)) == body
    with pytest.raises(FrameError, match="checksum"):
        decode_frame(b"KV 110.0*B2\r\n")


@pytest.mark.parametrize(
    ("reply", "match"),
    [
        (b"OK ID? MOCK 1.0*00\r\n", "checksum 00 does not match"),  # corrupted checksum
        (b"OK ID? MOCK 1.0\r\n", "checksum"),  # none at all
        (b"\xff\xfe\x00garbage*ZZ\r\n", "checksum"),
        (encode_frame("OK KV 110"), "another command"),
        (encode_frame("HELLO THERE"), "neither"),
    ],
)
def test_link_rejects_bad_replies(reply: bytes, match: str) -> None:
    replies = [reply, encode_frame("OK ID? MOCK 1.0")]
    with raw_pty(lambda _line: replies.pop(0)) as port:
        link = SerialLink(port, device="gen0")
        try:
            with pytest.raises(DeviceError, match=match) as caught:
                link.request("ID?", timeout_s=0.5)
            assert "gen0" in str(caught.value) and "'ID?'" in str(caught.value)
            assert not isinstance(caught.value, DeviceTimeout)
            # the link is usable again: the next request gets its good reply
            assert link.request("ID?", timeout_s=0.5).fields == ("MOCK", "1.0")
        finally:
            link.close()


def test_link_times_out_on_silence() -> None:
    with raw_pty(lambda _line: b"OK ID?") as port:  # a partial line, never finished
        link = SerialLink(port, device="gen0")
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeout, match=r"gen0: no reply to 'ID\?' within 0.2 s") as e:
            link.request("ID?", timeout_s=0.2)
        assert 0.2 <= time.monotonic() - t0 < 0.35
        assert "partial line b'OK ID?'" in str(e.value)
        link.close()
        link.close()


def test_link_over_a_port_without_a_file_descriptor() -> None:
    """pyserial URLs without a descriptor (loop:// echoes what is written) go through
    pyserial's read and write: the echoed request is read back whole and refused as a reply."""
    link = SerialLink("loop://", device="gen0")
    try:
        with pytest.raises(DeviceError, match=r"bad reply to 'ID\?': neither .*ID\?\*CC"):
            link.request("ID?", timeout_s=0.5)
    finally:
        link.close()


# -- generator ---------------------------------------------------------------------------------


@pytest.fixture
def devices() -> Iterator[ExitStack]:
    with ExitStack() as stack:
        yield stack


def generator(devices: ExitStack, **mock_args) -> tuple[MockGenerator, SerialGenerator]:
    mock = devices.enter_context(MockGenerator(**({"time_scale": 0.0} | mock_args)))
    driver = SerialGenerator(mock.port, name="gen0")
    devices.callback(driver.close)
    driver.connect(timeout_s=1.0)
    return mock, driver


def test_generator_expose_returns_technique_and_sequence(devices: ExitStack) -> None:
    delivered = []
    mock, gen = generator(devices, on_exposure=lambda *a: delivered.append(a))
    assert isinstance(gen, XrayGenerator)
    assert gen.ident == "MOCKGEN 1.0"
    status = gen.status(timeout_s=0.5)
    assert status.technique is None and not status.ready and status.interlocks_closed
    gen.set_technique(TECHNIQUE, timeout_s=0.5)
    t0 = time.monotonic()
    gen.prepare(timeout_s=1.0)
    assert time.monotonic() - t0 >= 0.045  # the mock's 0.05 s warm-up
    assert gen.status(timeout_s=0.5).ready
    assert gen.expose(timeout_s=0.5).technique == TECHNIQUE
    second = gen.expose(timeout_s=0.5)
    assert second.sequence == 2 and second.technique == TECHNIQUE
    assert delivered == [(110.0, 10.0, 20.0, 1), (110.0, 10.0, 20.0, 2)]
    status = gen.status(timeout_s=0.5)
    assert status.exposures == 2 and status.technique == TECHNIQUE
    names = mock.event_names()
    assert names[names.index("xray_on") :][:3] == ["xray_on", "xray_off", "exposure"]


def test_generator_real_time_pulse(devices: ExitStack) -> None:
    mock, gen = generator(devices, time_scale=1.0)
    gen.set_technique(Technique(80.0, 5.0, 100.0), timeout_s=0.5)
    gen.prepare(timeout_s=1.0)
    t0 = time.monotonic()
    gen.expose(timeout_s=1.0)
    assert 0.095 <= time.monotonic() - t0 < 0.3
    on = next(e for e in mock.events() if e.name == "xray_off").info["on_s"]
    assert on == pytest.approx(0.1, abs=0.03)


@pytest.mark.parametrize(
    ("technique", "value", "limit"),
    [
        (Technique(160.0, 10.0, 20.0), "160", "above limit 150"),
        (Technique(30.0, 10.0, 20.0), "30", "below limit 40"),
        (Technique(110.0, 600.0, 20.0), "600", "above limit 500"),
        (Technique(110.0, 10.0, 0.5), "0.5", "below limit 1"),
    ],
)
def test_generator_technique_out_of_range(
    devices: ExitStack, technique: Technique, value: str, limit: str
) -> None:
    mock, gen = generator(devices)
    with pytest.raises(DeviceError, match="RANGE") as caught:
        gen.set_technique(technique, timeout_s=0.5)
    assert value in str(caught.value) and limit in str(caught.value)
    assert "gen0" in str(caught.value)
    with pytest.raises(DeviceError):  # no technique, so PREP is refused
        gen.prepare(timeout_s=0.5)
    with pytest.raises(DeviceError, match="NOTECH"):
        gen.expose(timeout_s=0.5)
    assert mock.exposures == 0 and "xray_on" not in mock.event_names()


def test_generator_refuses_with_door_open(devices: ExitStack) -> None:
    mock, gen = generator(devices)
    gen.set_technique(TECHNIQUE, timeout_s=0.5)
    gen.prepare(timeout_s=1.0)
    mock.set_interlock("door", False)
    assert gen.status(timeout_s=0.5).interlocks == {"estop": True, "door": False, "deadman": True}
    with pytest.raises(DeviceError, match=r"INTERLOCK.*door"):
        gen.expose(timeout_s=0.5)
    assert mock.exposures == 0 and gen.status(timeout_s=0.5).exposures == 0
    assert "xray_on" not in mock.event_names() and mock.event_names()[-1] == "refused"
    mock.set_interlock("door", True)
    assert gen.expose(timeout_s=0.5).sequence == 1


def test_generator_refuses_unprepared_and_door_opening_at_exposure(devices: ExitStack) -> None:
    mock, gen = generator(devices, interlock_open_at_exposure=2)
    gen.set_technique(TECHNIQUE, timeout_s=0.5)
    with pytest.raises(DeviceError, match="NOTREADY"):
        gen.expose(timeout_s=0.5)  # EXP 1: not prepared
    gen.prepare(timeout_s=1.0)
    with pytest.raises(DeviceError, match="door"):
        gen.expose(timeout_s=0.5)  # EXP 2: the door opens just before
    assert mock.exposures == 0 and "xray_on" not in mock.event_names()


def test_generator_timeout_fault_then_abort(devices: ExitStack) -> None:
    mock, gen = generator(devices, timeout_at_exposure=1)
    gen.set_technique(TECHNIQUE, timeout_s=0.5)
    gen.prepare(timeout_s=1.0)
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout, match=r"gen0: no reply to 'EXP' within 0.3 s"):
        gen.expose(timeout_s=0.3)
    assert 0.3 <= time.monotonic() - t0 < 0.45
    n_before = len(mock.events())
    gen.abort(timeout_s=0.5)
    after = [e.name for e in mock.events()[n_before:]]
    assert after == ["abort", "xray_off"] and not mock.xray_on
    assert mock.exposures == 0
    gen.prepare(timeout_s=1.0)  # ABORT released READY; the generator serves on
    assert gen.expose(timeout_s=0.5).sequence == 1


def test_generator_stuck_on_is_switched_off_by_abort(devices: ExitStack) -> None:
    mock, gen = generator(devices, stuck_on_at_exposure=1)
    gen.set_technique(TECHNIQUE, timeout_s=0.5)
    gen.prepare(timeout_s=1.0)
    with pytest.raises(DeviceTimeout):
        gen.expose(timeout_s=0.2)
    assert mock.xray_on and gen.status(timeout_s=0.5).technique == TECHNIQUE
    gen.abort(timeout_s=0.5)
    assert not mock.xray_on and mock.exposures == 0
    names = mock.event_names()
    assert names[names.index("xray_on") :] == ["xray_on", "abort", "xray_off"]


def test_generator_abort_cuts_a_pulse_from_another_thread(devices: ExitStack) -> None:
    mock, gen = generator(devices, time_scale=1.0)
    gen.set_technique(Technique(110.0, 10.0, 1000.0), timeout_s=0.5)
    gen.prepare(timeout_s=1.0)
    outcome: list[BaseException] = []

    def fire() -> None:
        try:
            gen.expose(timeout_s=2.0)
        except DeviceError as exc:
            outcome.append(exc)

    thread = threading.Thread(target=fire)
    thread.start()
    while not mock.xray_on:
        time.sleep(0.005)
    t0 = time.monotonic()
    gen.abort(timeout_s=0.5)  # written at once, not queued behind the outstanding EXP
    assert time.monotonic() - t0 < 0.1 and not mock.xray_on
    thread.join(timeout=1.0)
    assert len(outcome) == 1 and "ABORTED" in str(outcome[0])
    assert mock.exposures == 0
    names = mock.event_names()
    assert names[names.index("xray_on") :] == ["xray_on", "abort", "xray_off"]


def test_generator_abort_needs_no_earlier_state(devices: ExitStack) -> None:
    mock = devices.enter_context(MockGenerator(time_scale=0.0))
    gen = SerialGenerator(mock.port)
    gen.abort(timeout_s=0.5)  # never connected
    gen.close()
    gen.abort(timeout_s=0.5)  # after close
    gen.close()
    assert mock.event_names().count("xray_off") == 4  # two aborts, and one per close


def test_mock_generator_rejects_bad_checksum(devices: ExitStack) -> None:
    mock = devices.enter_context(MockGenerator())
    port = devices.enter_context(serial.Serial(mock.port, timeout=0.5))
    port.write(b"KV 100*00\r\n")
    assert decode_frame(port.readline()).startswith("ERR KV CHECKSUM")
    port.write(encode_frame("KV 100"))
    assert decode_frame(port.readline()) == "OK KV 100"


# -- stage -------------------------------------------------------------------------------------


def stage(devices: ExitStack, **mock_args) -> tuple[MockStage, SerialStage]:
    mock = devices.enter_context(MockStage(**mock_args))
    driver = SerialStage(mock.port, name="stage0")
    devices.callback(driver.close)
    driver.connect(timeout_s=1.0)
    return mock, driver


def test_stage_position(devices: ExitStack) -> None:
    _, st = stage(devices, start=(12.5, 300.0))
    assert isinstance(st, Arm) and st.joints == ("rotary", "lift")
    reading = st.state(timeout_s=0.5)
    np.testing.assert_allclose(reading.q, [12.5, 300.0])
    assert not reading.protective_stop and st.controller_t_s is not None
    assert abs(reading.t_s - time.monotonic()) < 0.1


def test_stage_move_arrives_within_limits(devices: ExitStack) -> None:
    mock, st = stage(devices, start=(0.0, 100.0))
    t0 = time.monotonic()
    st.move_to(np.array([5.0, 120.0]), timeout_s=3.0)
    elapsed = time.monotonic() - t0
    # rotary: 5 deg at 30 deg/s^2 needs 2*sqrt(5/30) = 0.82 s from rest to rest
    assert 0.8 <= elapsed < 1.2
    np.testing.assert_allclose(st.state(timeout_s=0.5).q, [5.0, 120.0], atol=0.01)
    assert "arrived" in mock.event_names()


def test_stage_move_refusals(devices: ExitStack) -> None:
    mock, st = stage(devices)
    with pytest.raises(DeviceError, match="RANGE lift 900 mm above limit 800"):
        st.move_to(np.array([0.0, 900.0]), timeout_s=1.0)
    with pytest.raises(DeviceTimeout, match="needs"):
        st.move_to(np.array([90.0, 0.0]), timeout_s=0.5)  # 4 s move: stopped at once
    time.sleep(0.05)
    assert not mock.moving and abs(mock.position[0]) < 0.1


def test_stage_servo_stream_follows(devices: ExitStack) -> None:
    mock, st = stage(devices, start=(0.0, 100.0))
    dt = 0.01
    worst = 0.0
    for k in range(1, 41):  # 10 deg/s and 50 mm/s ramps, 0.4 s
        t_k = time.monotonic()
        st.servo(np.array([0.1 * k, 100.0 + 0.5 * k]), dt_s=dt)
        if k % 5 == 0:
            reading = st.state(timeout_s=0.5)
            worst = max(worst, abs(reading.q[0] - 0.1 * k))
        time.sleep(max(0.0, dt - (time.monotonic() - t_k)))
    assert 0.0 < worst < 1.0  # lags by about (lag + dt) * speed, never jumps ahead
    time.sleep(0.15)
    np.testing.assert_allclose(st.state(timeout_s=0.5).q, [4.0, 120.0], atol=0.01)
    assert mock.servo_count == 40
    st.stop()


def test_stage_protective_stop(devices: ExitStack) -> None:
    mock, st = stage(devices, protective_stop_after_servo=3)
    for k in range(3):
        st.servo(np.array([0.1 * (k + 1), 0.0]), dt_s=0.01)
    with pytest.raises(ProtectiveStop, match="stage0"):
        st.state(timeout_s=0.5)
    with pytest.raises(ProtectiveStop, match="PSTOP"):
        st.servo(np.array([0.5, 0.0]), dt_s=0.01)
    with pytest.raises(ProtectiveStop):
        st.move_to(np.array([0.0, 0.0]), timeout_s=1.0)
    assert mock.servo_count == 3
    mock.clear_protective_stop()
    assert not st.state(timeout_s=0.5).protective_stop

"""The Spellman driver against the mock Spellman supply over real ptys: framing, checksum,
technique limits, host-timed pulses, interlock, abort, and a simulated scan on that protocol.

Timing bounds are the pulse width plus the link's measured round trip (:func:`round_trip`)
and :data:`LOAD_MARGIN_S`, the scheduling delay a thread may see on a loaded 2-core machine."""

from __future__ import annotations

import csv
import inspect
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack
from pathlib import Path

import pytest
import serial
import yaml

from configs import CONFIGS
from scanner.hardware import DeviceError, DeviceTimeout, Technique, XrayGenerator
from scanner.inputs import read_inputs
from scanner.scan import ScanFault, ScanSettings
from scanner.serial_link import FrameError, SerialLink
from scanner.session import run_session
from scanner.spellman import SPELLMAN_FRAMING, SpellmanFraming, SpellmanGenerator
from scanner.spellman import spellman_checksum as host_checksum
from scanner.study_folder import Study
from sim.spellman import MockSpellman
from sim.spellman import SpellmanFraming as MockFraming
from sim.spellman import spellman_checksum as mock_checksum
from tests.scanner.test_ur_scan import tiny_protocol

LOAD_MARGIN_S = 0.05
"""Scheduling delay a waiting thread may see on a loaded 2-core machine, s."""
TECHNIQUE = Technique(kv=110.0, ma=51.0, ms=15.0)
KV_FULL, MA_FULL = 150.0, 100.0


# -- framing -----------------------------------------------------------------------------------


def test_checksum_of_a_hand_computed_frame() -> None:
    # "10,4095,": 0x31+0x30+0x2C+0x34+0x30+0x39+0x35+0x2C = 395 = 0x18B; two's complement
    # -0x18B = ...0x75 (8 bits); & 0x7F = 0x75; | 0x40 = 0x75: "u"
    assert host_checksum(b"10,4095,") == 0x75 == mock_checksum(b"10,4095,")
    assert SPELLMAN_FRAMING.encode("10,4095") == b"\x0210,4095,u\x03"
    # "98,1,": 0x39+0x38+0x2C+0x31+0x2C = 250; -250 & 0xFF = 0x06; & 0x7F | 0x40 = 0x46: "F"
    assert SPELLMAN_FRAMING.encode("98,1") == b"\x0298,1,F\x03"
    for content in (b"22,", b"98,0,", b"60,3003,", b"10,!,3,", b"26,X4171,"):
        assert 0x40 <= host_checksum(content) <= 0x7F
        assert host_checksum(content) == mock_checksum(content)  # independent implementations
    mock = MockFraming()
    for body in ("98,$,", "60,3003,", "10,!,3,"):
        frame = mock.encode(body)
        reply = SPELLMAN_FRAMING.decode(frame, "x")
        assert reply.line == body and SPELLMAN_FRAMING.frame_end(frame + b"\x02") == len(frame)
    assert SPELLMAN_FRAMING.decode(mock.encode("60,3003,"), "60").fields == ("3003",)
    refusal = SPELLMAN_FRAMING.decode(mock.encode("10,!,3,"), "10,5000")
    assert not refusal.ok and refusal.code == "3" and refusal.message == "parameter out of range"
    assert mock.decode(SPELLMAN_FRAMING.encode("10,4095")) == ("10", ["4095"])
    with pytest.raises(FrameError, match="checksum 0x76 does not match the content's 0x75"):
        SPELLMAN_FRAMING.decode(b"\x0210,4095,v\x03", "10,4095")
    with pytest.raises(ValueError, match="two-digit"):
        SPELLMAN_FRAMING.request_text("ABORT", ())


class _BadChecksum(SpellmanFraming):
    """Frames whose checksum is off by one."""

    def encode(self, text: str) -> bytes:
        frame = bytearray(super().encode(text))
        frame[-2] ^= 0x01
        return bytes(frame)


def test_a_frame_with_a_bad_checksum_gets_no_reply(devices: ExitStack) -> None:
    mock = devices.enter_context(MockSpellman())
    port = devices.enter_context(serial.Serial(mock.port, timeout=0.2))
    port.write(b"\x0222,q\x03")  # the checksum of "22," is "p"
    assert port.read(16) == b""
    port.write(b"\x0222,p\x03")
    status = MockFraming().encode("22,0,0,0,0,")
    assert port.read(len(status)) == status
    assert mock.event_names() == ["ignored"]

    link = SerialLink(mock.port, device="gen0", framing=_BadChecksum())
    devices.callback(link.close)
    t0 = time.monotonic()
    with pytest.raises(
        DeviceTimeout, match=r"gen0: no reply to '26' within 0.2 s \(received nothing"
    ):
        link.request("26", timeout_s=0.2)
    assert 0.2 <= time.monotonic() - t0 < 0.2 + LOAD_MARGIN_S
    assert mock.event_names() == ["ignored", "ignored"]


def test_refusals_name_the_request_and_code(devices: ExitStack) -> None:
    mock = devices.enter_context(MockSpellman())
    link = SerialLink(mock.port, device="gen0", framing=SPELLMAN_FRAMING)
    devices.callback(link.close)
    for request, code in ((("10", 4096), "3"), (("42",), "2"), (("10", "x"), "1")):
        reply = link.request(*request, timeout_s=0.5)
        assert not reply.ok and reply.code == code
        assert str(link.refused(reply)).startswith(f"gen0: {','.join(map(str, request))!r} refused")
    assert link.request("98", 1, timeout_s=0.5).code == "2"  # local mode: HV on refused
    assert not mock.xray_on


# -- the driver --------------------------------------------------------------------------------


@pytest.fixture
def devices() -> Iterator[ExitStack]:
    with ExitStack() as stack:
        yield stack


def generator(
    devices: ExitStack, sent: list[str] | None = None, *, mock_args=None, **driver_args
) -> tuple[MockSpellman, SpellmanGenerator]:
    mock = devices.enter_context(
        MockSpellman(kv_full_scale=KV_FULL, ma_full_scale=MA_FULL, **(mock_args or {}))
    )
    driver = SpellmanGenerator(
        mock.port,
        name="gen0",
        kv_full_scale=KV_FULL,
        ma_full_scale=MA_FULL,
        on_sent=None if sent is None else lambda body, _t: sent.append(body),
        **driver_args,
    )
    devices.callback(driver.close)
    driver.connect(timeout_s=1.0)
    return mock, driver


def round_trip(gen: SpellmanGenerator) -> float:
    """The slowest of a few status requests, s: the link latency bounds are built on."""
    slowest = 0.0
    for _ in range(5):
        t0 = time.monotonic()
        gen.status(timeout_s=0.5)
        slowest = max(slowest, time.monotonic() - t0)
    return slowest


def prepared(devices: ExitStack, technique: Technique = TECHNIQUE, **kwargs):
    mock, gen = generator(devices, **kwargs)
    gen.set_technique(technique, timeout_s=0.5)
    gen.prepare(timeout_s=0.5)
    return mock, gen


def test_expose_delivers_the_technique_in_order(devices: ExitStack) -> None:
    delivered, sent = [], []
    mock, gen = generator(devices, sent, mock_args={"on_exposure": lambda *a: delivered.append(a)})
    assert isinstance(gen, XrayGenerator)
    assert gen.ident == "MOCKSPELLMAN 1.0" and mock.remote
    assert sent == ["99 1", "22", "26", "23"]
    status = gen.status(timeout_s=0.5)
    assert status.technique is None and not status.ready and status.interlocks_closed
    gen.set_technique(TECHNIQUE, timeout_s=0.5)
    gen.prepare(timeout_s=0.5)
    assert gen.status(timeout_s=0.5).ready
    rt = round_trip(gen)
    first = gen.expose(timeout_s=1.0)
    second = gen.expose(timeout_s=1.0)
    assert (first.sequence, second.sequence) == (1, 2)
    for exposure in (first, second):
        assert exposure.technique.kv == 110.0  # 3003 counts of 150 kV
        assert exposure.technique.ma == pytest.approx(51.0, abs=MA_FULL / 4095)  # 2088 counts
        assert 15.0 <= exposure.technique.ms <= 15.0 + 1e3 * (2 * rt + LOAD_MARGIN_S)
    assert [(kv, seq) for kv, _, _, seq in delivered] == [(110.0, 1), (110.0, 2)]
    for (_, _, ms, _), exposure in zip(delivered, (first, second), strict=True):
        assert ms == pytest.approx(exposure.technique.ms, abs=1e3 * (rt + LOAD_MARGIN_S))
    names = mock.event_names()
    assert names[names.index("xray_on") :] == ["xray_on", "xray_off", "exposure"] * 2
    assert [e.info["reason"] for e in mock.events() if e.name == "xray_off"] == ["command"] * 2
    on = sent.index("98 1")
    pulse = sent[on : sent.index("98 0", on) + 2]  # the first pulse, and its check after
    assert pulse[:2] == ["98 1", "22"] and pulse[-2:] == ["98 0", "22"]
    assert {"60", "61"} <= set(pulse)  # the monitors read while HV is on
    status = gen.status(timeout_s=0.5)
    assert status.exposures == 2
    assert status.technique == Technique(110.0, 2088 * MA_FULL / 4095, 15.0)


def test_a_real_time_pulse_lasts_its_width(devices: ExitStack) -> None:
    mock, gen = prepared(devices, Technique(80.0, 5.0, 200.0))
    rt = round_trip(gen)
    t0 = time.monotonic()
    exposure = gen.expose(timeout_s=1.0)
    elapsed = time.monotonic() - t0
    assert 0.2 <= exposure.technique.ms * 1e-3 <= 0.2 + 2 * rt + LOAD_MARGIN_S
    assert 0.2 <= elapsed <= 0.2 + 6 * rt + LOAD_MARGIN_S  # status, HV on, HV off, status
    on_s = next(e for e in mock.events() if e.name == "xray_off").info["on_s"]
    assert on_s == pytest.approx(exposure.technique.ms * 1e-3, abs=rt + LOAD_MARGIN_S)


@pytest.mark.parametrize(
    ("technique", "words"),
    [
        (Technique(160.0, 10.0, 20.0), "kV 160 above limit 150"),
        (Technique(30.0, 10.0, 20.0), "kV 30 below limit 40"),
        (Technique(110.0, 120.0, 20.0), "mA 120 above limit 100"),
        (Technique(110.0, 0.2, 20.0), "mA 0.2 below limit 0.5"),
        (Technique(110.0, 10.0, 2.0), "ms 2 below limit 5"),
        (Technique(110.0, 10.0, 2000.0), "ms 2000 above limit 1000"),
        (Technique(float("nan"), 10.0, 20.0), "kV nan is not a number"),
    ],
)
def test_technique_out_of_range_is_refused_before_sending(
    devices: ExitStack, technique: Technique, words: str
) -> None:
    sent: list[str] = []
    mock, gen = generator(devices, sent)
    sent.clear()
    with pytest.raises(DeviceError, match=f"gen0: {words}: nothing sent"):
        gen.set_technique(technique, timeout_s=0.5)
    assert sent == [] and "set" not in mock.event_names()
    with pytest.raises(DeviceError, match="no technique set"):
        gen.prepare(timeout_s=0.5)
    with pytest.raises(DeviceError, match="'98,1' not sent: no technique set"):
        gen.expose(timeout_s=0.5)
    assert "98 1" not in sent and "xray_on" not in mock.event_names()


def test_an_open_interlock_refuses_and_nothing_fires(devices: ExitStack) -> None:
    sent: list[str] = []
    mock, gen = prepared(devices, sent=sent)
    mock.set_interlock(False)
    status = gen.status(timeout_s=0.5)
    assert status.interlocks == {"interlock": False} and not status.ready
    with pytest.raises(DeviceError, match="gen0: '98,1' not sent: interlock open"):
        gen.expose(timeout_s=0.5)
    assert "98 1" not in sent and "xray_on" not in mock.event_names()
    mock.set_interlock(True)
    assert gen.expose(timeout_s=0.5).sequence == 1


def test_an_interlock_opening_at_hv_on_is_refused_by_the_supply(devices: ExitStack) -> None:
    """The interlock opens after the driver's status check, just before ``98,1``: the supply
    refuses it, nothing fires, the driver says why."""
    mock, gen = prepared(devices, mock_args={"interlock_open_at_exposure": 1})
    with pytest.raises(DeviceError) as caught:
        gen.expose(timeout_s=0.5)
    assert str(caught.value) == (
        "gen0: '98,1' refused: 2 invalid command: interlock open; nothing fired"
    )
    assert "xray_on" not in mock.event_names() and mock.exposures == 0


def test_local_mode_and_faults_refuse(devices: ExitStack) -> None:
    mock, gen = prepared(devices)
    mock.set_remote(False)
    assert not gen.status(timeout_s=0.5).ready
    with pytest.raises(DeviceError, match="not sent: the supply is in local mode"):
        gen.expose(timeout_s=0.5)
    with pytest.raises(DeviceError, match="not prepared: the supply is in local mode"):
        gen.prepare(timeout_s=0.5)
    gen.connect(timeout_s=0.5)  # takes remote control again
    mock.set_fault("OVER_TEMPERATURE")
    assert gen.status(timeout_s=0.5).fault == "OVER_TEMPERATURE"
    with pytest.raises(DeviceError, match="not sent: fault OVER_TEMPERATURE latched"):
        gen.expose(timeout_s=0.5)
    with pytest.raises(DeviceError, match="not prepared: fault OVER_TEMPERATURE latched"):
        gen.prepare(timeout_s=0.5)
    gen.reset_faults(timeout_s=0.5)
    gen.prepare(timeout_s=0.5)
    assert gen.expose(timeout_s=0.5).sequence == 1
    assert "xray_on" in mock.event_names()


def pulse_running(devices: ExitStack, **options):
    """A 1 s pulse exposing in a thread for 50 ms already: (mock, driver, the link's round trip,
    the list the exposure's error goes to, the thread)."""
    mock, gen = prepared(devices, Technique(110.0, 10.0, 1000.0), **options)
    rt = round_trip(gen)
    outcome: list[BaseException] = []
    thread = threading.Thread(target=lambda: _expose_into(gen, outcome))
    thread.start()
    while not mock.xray_on:
        time.sleep(0.002)
    time.sleep(0.05)
    return mock, gen, rt, outcome, thread


@pytest.mark.parametrize("cause", ["interlock", "fault"])
def test_an_interlock_or_fault_mid_pulse_cuts_it(devices: ExitStack, cause: str) -> None:
    mock, gen, rt, outcome, thread = pulse_running(devices, poll_s=0.005)
    t_cut = time.monotonic()
    if cause == "interlock":
        mock.set_interlock(False)
    else:
        mock.set_fault("ARC")
    thread.join(timeout=1.0)
    noticed = time.monotonic() - t_cut
    assert not thread.is_alive() and noticed < 0.005 + 6 * rt + LOAD_MARGIN_S  # poll, off, check
    (error,) = outcome
    reason = "interlock opened" if cause == "interlock" else "fault ARC"
    assert str(error).startswith("gen0: pulse cut after")
    assert f"{reason}; X-ray off confirmed; not counted" in str(error)
    assert not mock.xray_on and gen.status(timeout_s=0.5).exposures == 0
    off = next(e for e in mock.events() if e.name == "xray_off")
    assert off.info["reason"] == cause and off.info["on_s"] < 0.5
    latched = "INTERLOCK" if cause == "interlock" else "ARC"
    assert mock.faults == (latched,)
    with pytest.raises(DeviceError, match=f"fault {latched} latched"):
        gen.prepare(timeout_s=0.5)


def _expose_into(gen: SpellmanGenerator, outcome: list[BaseException]) -> None:
    try:
        gen.expose(timeout_s=2.0)
    except DeviceError as exc:
        outcome.append(exc)


def test_abort_from_another_thread_cuts_a_long_pulse(devices: ExitStack) -> None:
    mock, gen, rt, outcome, thread = pulse_running(devices)
    t0 = time.monotonic()
    gen.abort(timeout_s=0.5)  # written at once, even while the pulse's poll waits for a reply
    assert time.monotonic() - t0 < 2 * rt + LOAD_MARGIN_S and not mock.xray_on
    thread.join(timeout=1.0)
    assert not thread.is_alive() and time.monotonic() - t0 < 4 * rt + LOAD_MARGIN_S
    (error,) = outcome
    assert "aborted; X-ray off confirmed; not counted" in str(error)
    names = mock.event_names()
    assert names[names.index("xray_on") :] == ["xray_on", "xray_off", "exposure", "abort"]
    off = next(e for e in mock.events() if e.name == "xray_off")
    assert off.info["on_s"] < 0.5
    status = gen.status(timeout_s=0.5)
    assert status.exposures == 0 and not status.ready  # abort drops prepared
    with pytest.raises(DeviceError, match="not prepared"):
        gen.expose(timeout_s=0.5)


def test_hv_on_unanswered_times_out_and_switches_off(devices: ExitStack) -> None:
    mock, gen = prepared(devices, mock_args={"timeout_at_exposure": 1}, overrun_s=0.05)
    rt = round_trip(gen)
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout) as caught:
        gen.expose(timeout_s=1.0)
    message = str(caught.value)
    assert message.startswith("gen0: no reply to '98,1' within 0.065 s")
    assert "X-ray off confirmed" in message
    assert time.monotonic() - t0 < 0.065 + 4 * rt + LOAD_MARGIN_S  # pulse + overrun, off
    names = mock.event_names()
    assert names[names.index("ignored") :] == ["ignored", "abort"]
    assert gen.expose(timeout_s=1.0).sequence == 1  # the supply serves on


def test_permit_refusal_sends_nothing_and_abort_needs_no_state(devices: ExitStack) -> None:
    sent: list[str] = []
    mock, gen = prepared(devices, sent=sent)

    def stop() -> None:
        raise RuntimeError("operator stop")

    with pytest.raises(RuntimeError, match="operator stop"):
        gen.expose(timeout_s=0.5, permit=stop)
    assert "98 1" not in sent and "xray_on" not in mock.event_names()
    fresh = SpellmanGenerator(mock.port)
    fresh.abort(timeout_s=0.5)  # never connected
    fresh.close()
    fresh.abort(timeout_s=0.5)  # after close
    fresh.close()
    fresh.close()
    assert mock.event_names().count("abort") == 4  # two aborts, and a close after each


# -- a simulated scan on the Spellman protocol -------------------------------------------------


def spellman_inputs(tmp: Path, **faults):
    path = tmp / "sim-spellman.yaml"
    spec = {"seed": 3, "generator_protocol": "spellman", "faults": faults}
    path.write_text(yaml.safe_dump(spec))
    return read_inputs(
        tiny_protocol(),  # 16 views of 64^2
        CONFIGS / "scanner.yaml",
        "sim",
        path,
        CONFIGS / "phantoms" / "knee.yaml",
        phantom_voxel_mm=3.0,
    )


def _rows(study: Path, name: str) -> list[dict[str, str]]:
    with open(study / "scan" / f"{name}-1.csv", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def test_a_simulated_scan_on_the_spellman_protocol_completes(tmp_path: Path) -> None:
    study = run_session(tmp_path / "study", spellman_inputs(tmp_path))
    scan = study.stage("scan")
    assert scan["status"] == "complete" and scan["views"] == 16 and study.verify() == []
    with open(tmp_path / "study" / "scan" / "exposure_log.csv", encoding="utf-8") as fh:
        log = list(csv.DictReader(fh))
    assert [int(r["sequence"]) for r in log] == list(range(1, 17))
    assert all(float(r["kv"]) == 110.0 for r in log)
    overrun_s = inspect.signature(SpellmanGenerator).parameters["overrun_s"].default
    assert all(15.0 <= float(r["ms"]) < 15.0 + 1e3 * (overrun_s + LOAD_MARGIN_S) for r in log)
    commands = [r["command"] for r in _rows(tmp_path / "study", "generator_commands")]
    assert commands[:4] == ["99 1", "22", "26", "23"] and commands.count("98 1") == 16
    events = [r["event"] for r in _rows(tmp_path / "study", "device_events")]
    assert events.count("xray_on") == events.count("xray_off") == 16


def test_a_spellman_generator_timeout_ends_safe_with_the_x_ray_off_first(tmp_path: Path) -> None:
    with pytest.raises(ScanFault) as caught:
        run_session(
            tmp_path / "study",
            spellman_inputs(tmp_path, generator_timeout_at_view=5),
            settings=ScanSettings(device_timeout_s=1.0),
        )
    assert "no reply to '98,1'" in caught.value.reason and caught.value.views_stored == 5
    study = Study.open(tmp_path / "study")
    assert study.stage("scan")["status"] == "incomplete" and study.verify() == []
    events = [
        (int(r["sequence"]), r["device"], r["event"])
        for r in _rows(tmp_path / "study", "device_events")
    ]
    ignored = next(seq for seq, who, what in events if who == "generator" and what == "ignored")
    after = [(seq, who, what) for seq, who, what in events if seq > ignored]
    offs = [seq for seq, who, what in after if who == "generator" and what == "abort"]
    stops = [seq for seq, _, what in after if what == "stop"]
    # the driver's own HV off after the unanswered 98,1, then SAFE's, then the arms stop (the
    # backend's close switches HV off and stops them once more)
    assert len([seq for seq in offs if seq < min(stops)]) == 2
    assert not [e for e in after if e[2] == "xray_on"]
    assert {who for _, who, what in after if what == "stop"} >= {
        "stage",
        "source_arm",
        "detector_arm",
    }

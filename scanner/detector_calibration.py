"""Detector calibration: dark and flood frames acquired on the scanner, maps derived and stored.

The acquisition follows the scan's safety model. Nothing is exposed before the interlocks read
closed and the operator has confirmed that nothing is in the beam; every pulse is commanded
through the operator's stop (:class:`scanner.stop.StopRequest`), whose watchdog turns the
X-ray off itself when the loop has not; any failure turns the X-ray off and stops the arms
(:func:`scanner.scan.stop_safely`) before it is raised. The arms do not move: the panel is
flooded wherever they stand. Order: ``frames`` darks, the generator prepared, ``frames``
floods, then :data:`AFTER_DARKS` darks whose first measures the lag
(:func:`scanner.corrections.derive_maps`).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from scanner.corrections import MapsError, PanelMaps, derive_maps, maps_path
from scanner.hardware import Backend, DeviceError, Technique
from scanner.inputs import SessionInputs
from scanner.registry import Rig, backend_kind, nothing_in_the_beam
from scanner.scan import OperatorDeclined, PreflightError, ScanSettings, stop_safely
from scanner.stop import StopRequest, stop_signals
from trajectories.model import ScannerModel
from trajectories.move import park_pose

AFTER_DARKS = 2
"""Dark frames read after the floods (the first holds the floods' lag)."""
MIN_FRAMES = 4
MAX_FRAMES = 256


def calibrate_detector(
    backend: Backend,
    technique: Technique,
    frames: int,
    *,
    confirm: Callable[[str], bool] = lambda _q: True,
    progress: Callable[[int, int], None] = lambda _d, _t: None,
    settings: ScanSettings | None = None,
    stop: StopRequest | None = None,
) -> PanelMaps:
    """Acquire darks and floods on ``backend`` and derive the panel's maps (not saved).

    Args:
        backend: the devices, not yet connected (connected here, not closed).
        technique: the floods' technique (the scans' kV; maps refuse scans at another kV).
        frames: darks and floods to average, each (4..256).
        confirm: asks the operator; False before any pulse raises OperatorDeclined.
        progress: called with (frames read, frames in all).
        settings: device timeouts.
        stop: the operator's stop request.

    Returns:
        The maps of the backend's panel in its read-out mode.
    """
    if not MIN_FRAMES <= frames <= MAX_FRAMES:
        raise ValueError(f"frames must be in [{MIN_FRAMES}, {MAX_FRAMES}], got {frames}")
    settings = settings or ScanSettings()
    stop = stop or StopRequest()
    timeout = settings.device_timeout_s
    generator, detector = backend.generator, backend.detector
    for device in (*backend.groups, generator, detector):
        device.connect(timeout)
    generator.set_technique(technique, timeout)
    status = generator.status(timeout)
    if not status.interlocks_closed:
        opened = [name for name, closed in status.interlocks.items() if not closed]
        raise PreflightError(f"interlocks open: {opened or 'none reported'}")
    if status.fault:
        raise PreflightError(f"generator fault: {status.fault}")
    question = (
        f"Is the beam clear (nothing between the tube and the panel)? {frames} flood frames at "
        f"{technique.kv:g} kV, {technique.ma:g} mA, {technique.ms:g} ms"
    )
    with stop.interrupting():
        if not confirm(question):
            raise OperatorDeclined("operator declined the floods: nothing exposed")
    total = 2 * frames + AFTER_DARKS
    done = 0

    def read(expose: bool) -> np.ndarray:
        nonlocal done
        detector.arm(timeout)
        if expose:
            generator.expose(timeout, permit=lambda: stop.check(f"flood {done}: EXP"))
        frame = detector.read_frame(timeout)
        done += 1
        progress(done, total)
        return np.asarray(frame.counts)

    with stop.guarding(lambda: stop_safely(backend, timeout)) as guard, stop.deferring():
        try:
            darks = np.stack([read(False) for _ in range(frames)])
            stop.check("PREP")
            generator.prepare(settings.warmup_timeout_s)
            floods = np.stack([read(True) for _ in range(frames)])
            after = np.stack([read(False) for _ in range(AFTER_DARKS)])
        except BaseException as err:
            guard.acknowledge()
            problems = stop_safely(backend, timeout)
            if problems:
                raise DeviceError(f"{stop.explain(err)}; {'; '.join(problems)}") from err
            raise
    return derive_maps(
        darks,
        floods,
        after,
        serial=detector.serial,
        mode=detector.mode,
        kv=technique.kv,
        mas=technique.mas,
    )


def calibrate_session(
    inputs: SessionInputs,
    out: Path,
    frames: int,
    *,
    confirm: Callable[[str], bool] = lambda _q: True,
    progress: Callable[[int, int], None] = lambda _d, _t: None,
    say: Callable[[str], None] = lambda _m: None,
) -> tuple[PanelMaps, Path]:
    """``cbct detector-calibrate``: the panel of ``inputs``' backend calibrated in the read-out
    mode and at the technique of its protocol; the maps written under ``out``
    (:meth:`PanelMaps.save`, never over older ones). The simulated backend's panel sees
    nothing in the beam; the arms stay where they stand (the simulated ones at park)."""
    if not MIN_FRAMES <= frames <= MAX_FRAMES:
        raise ValueError(f"frames must be in [{MIN_FRAMES}, {MAX_FRAMES}], got {frames}")
    model = ScannerModel(inputs.scanner)
    e, panel = inputs.protocol.exposure, inputs.panel
    rig = Rig(
        model, park_pose(model), panel, inputs.protocol.orbit.sdd_mm, nothing_in_the_beam(panel)
    )
    backend, _ = backend_kind(inputs.backend_kind).open(inputs.backend, rig)
    stop = StopRequest()
    try:
        with stop_signals(stop):
            backend.detector.connect(ScanSettings().device_timeout_s)
            path = maps_path(out, backend.detector.serial, backend.detector.mode)
            if path.exists():
                raise MapsError(f"{path} exists: detector maps are never overwritten")
            say(f"panel {backend.detector.serial}, mode {backend.detector.mode}")
            technique = Technique(e.tube_kv, e.tube_ma, e.pulse_ms)
            maps = calibrate_detector(
                backend, technique, frames, confirm=confirm, progress=progress, stop=stop
            )
    finally:
        backend.close()
    return maps, maps.save(out)

"""The scan state machine: PREFLIGHT -> APPROACH -> ACQUIRE -> RETREAT -> DONE, or SAFE.

PREFLIGHT checks everything before anything moves: the plan (joint limits, clearance), the dose
of the views still to acquire against the protocol's limit, the devices (connected, generator
technique accepted, interlocks closed), the arms at the plan's start, and asks the operator.
APPROACH streams the planned approach and warms the tube up, then asks again before exposure.
ACQUIRE streams the planned scan; at each view's time it reads both arms and the stage, checks
that the realised view is the planned one within tolerance, that the interlocks are closed and
that the study's disk can take the view (its files' space allocated), and only then fires one
pulse, reads the frame and stores it with the joint state it was taken at
(:class:`scanner.storage.ScanStore`): its files are written and fsynced while the plan streams
on, the next view is exposed and its panel reads out; the pulse after that waits until they
are in place (:data:`VIEWS_STORING_AT_A_PULSE`: at most one acquired view is not yet on disk
when a pulse fires, and none whose storage is known to have failed). RETREAT streams
the planned retreat; DONE assembles the stack. Any failure (a device error, a protective stop,
an off-pose view, an open interlock, a full disk, the operator's stop) goes to SAFE: X-ray off
first, then every joint group stops, then what was acquired is flushed (and the space of a view
not acquired released) and the scan marked incomplete with the reason; ``cbct scan --resume``
continues with the views not yet stored.

The operator's stop (:mod:`scanner.stop`: Ctrl-C and the other stop signals) is a request that
every set-point and every ``EXP`` is checked against right before it is sent; from APPROACH on,
a watchdog switches the X-ray off and stops the arms itself when the loop has not reached SAFE
within a few milliseconds of the request.
"""

from __future__ import annotations

import enum
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from recon.config import ScanProtocol
from recon.geometry import DetectorSpec, View
from scanner.corrections import Corrector, PanelMaps
from scanner.hardware import Backend, DeviceError, Technique
from scanner.stop import StopRequest
from scanner.storage import PendingView, ScanStore, ViewRecord
from scanner.study_folder import Reservation, StudyError
from trajectories.model import ScannerModel
from trajectories.plan import Plan, view_at

SETTLE_POLL_S = 0.01
"""Re-read interval while arms settle onto a view's pose, s."""
GROUP_SLICES = (slice(0, 2), slice(2, 8), slice(8, 14))
"""Plan joint indices of the backend's groups: stage (rotary, lift), source arm, detector arm."""
VIEWS_STORING_AT_A_PULSE = 1
"""Acquired views whose files may still be being written and fsynced when the next pulse fires:
the view before it (its storage hidden behind that pulse and the panel's read-out; a power loss
then costs the dose of at most two views, the one on its way to disk and the one exposed)."""
_RESERVER = ThreadPoolExecutor(max_workers=1, thread_name_prefix="scan-reserve")
"""The thread that reserves the next view's files' space while a panel reads out."""
_STOPPERS = ThreadPoolExecutor(max_workers=len(GROUP_SLICES), thread_name_prefix="safe-stop")
"""Threads that stop the joint groups together in SAFE (their drivers wait on sockets, pipes
and serial ports with the GIL released)."""


class State(enum.Enum):
    PREFLIGHT = "preflight"
    APPROACH = "approach"
    ACQUIRE = "acquire"
    RETREAT = "retreat"
    DONE = "done"
    SAFE = "safe"


class ScanFault(RuntimeError):
    """The scan stopped in SAFE; ``state`` is where it failed, ``reason`` why."""

    def __init__(self, state: State, reason: str, views_stored: int, views: int) -> None:
        super().__init__(
            f"scan stopped in {state.value.upper()}: {reason} "
            f"({views_stored}/{views} views stored; X-ray off, arms stopped)"
        )
        self.state, self.reason = state, reason
        self.views_stored, self.views = views_stored, views


class PreflightError(ValueError):
    """A preflight check failed: nothing moved, nothing was exposed."""


class OperatorDeclined(RuntimeError):
    """The operator answered no."""


@dataclass(frozen=True)
class ScanSettings:
    """Acquisition tolerances and timeouts.

    Attributes:
        pose_tolerance_mm: largest focal-spot / panel-centre distance between the realised and
            the planned view at exposure, mm.
        pose_tolerance_deg: largest angle between realised and planned panel normals, deg.
        start_tolerance: largest joint distance from the plan's start, deg (mm for the lift).
        settle_s: longest wait for arms that lag behind a view's pose before refusing it, s.
        device_timeout_s: timeout of every device call, s.
        warmup_timeout_s: timeout of the generator's warm-up, s.
    """

    pose_tolerance_mm: float = 2.0
    pose_tolerance_deg: float = 0.5
    start_tolerance: float = 0.5
    settle_s: float = 0.25
    device_timeout_s: float = 2.0
    warmup_timeout_s: float = 30.0


@dataclass
class Progress:
    """What the console shows while acquiring."""

    views_done: int
    views: int
    dose_mas: float
    elapsed_s: float
    state: State


@dataclass
class Preflight:
    """The preflight summary the operator confirms."""

    views: int
    views_to_acquire: int
    duration_s: float
    dose_mas: float
    dose_limit_mas: float
    min_clearance_mm: float
    clearance_margin_mm: float
    technique: Technique

    def text(self) -> str:
        return (
            f"{self.views_to_acquire} of {self.views} views to acquire, motion "
            f"{self.duration_s:.1f} s, dose {self.dose_mas:.1f} mAs (limit "
            f"{self.dose_limit_mas:.1f}), technique {self.technique.kv:g} kV "
            f"{self.technique.ma:g} mA {self.technique.ms:g} ms, minimum clearance "
            f"{self.min_clearance_mm:.1f} mm (margin {self.clearance_margin_mm:.1f})"
        )


@dataclass
class ScanRun:
    """One execution of a plan on a backend into a study's scan store.

    Args:
        backend: the devices (connected by :meth:`run`).
        model: the scanner model the plan was made on.
        plan: the checked, timed plan.
        protocol: its protocol (technique, panel).
        store: where views go.
        settings: tolerances and timeouts.
        confirm: asks the operator a yes/no question; False stops before motion / exposure.
        progress: called after every stored view.
        on_view: called with each stored view (e.g. the rerun recording).
        truth: the true view matrix of the last pulse, where a simulator knows it.
        true_poses: the patient's bodies' true poses at the last pulse (``T_world_body`` by
            body), where a simulator knows them.
        close_backend: close the devices when the run ends (False: the caller closes them,
            e.g. after parking the arms).
        stop: the operator's stop request (a session routes the stop signals to it:
            :func:`scanner.stop.stop_signals`).
        maps: the panel's offset, gain, defect and lag maps (of its serial number and mode,
            made at the protocol's kV); every frame is corrected with them before its log.
    """

    backend: Backend
    model: ScannerModel
    plan: Plan
    protocol: ScanProtocol
    store: ScanStore
    settings: ScanSettings = field(default_factory=ScanSettings)
    confirm: Callable[[str], bool] = lambda _question: True
    progress: Callable[[Progress], None] = lambda _p: None
    on_view: Callable[[ViewRecord, np.ndarray], None] = lambda _r, _img: None
    truth: Callable[[], np.ndarray | None] = lambda: None
    true_poses: Callable[[], dict[str, np.ndarray] | None] = lambda: None
    close_backend: bool = True
    stop: StopRequest = field(default_factory=StopRequest)
    maps: PanelMaps | None = None
    state: State = State.PREFLIGHT
    transitions: list[tuple[float, State]] = field(default_factory=list)

    def __post_init__(self) -> None:
        self._storing: deque[tuple[PendingView, np.ndarray]] = deque()  # oldest first
        self._reserved: dict[int, Future[Reservation]] = {}  # views' files' space, by view
        self._unreported: list[tuple[ViewRecord, np.ndarray]] = []  # stored, not handed on
        e = self.protocol.exposure
        self.technique = Technique(e.tube_kv, e.tube_ma, e.pulse_ms)
        self.panel = DetectorSpec(
            rows=self.protocol.detector.rows,
            cols=self.protocol.detector.cols,
            pixel_pitch_mm=self.protocol.detector.pixel_pitch_mm,
        )
        self._started = time.perf_counter()

    # -- the machine --------------------------------------------------------------------

    def run(self) -> None:
        """Run the scan to DONE; raises PreflightError / OperatorDeclined / OperatorStop before
        anything moves, ScanFault after SAFE."""
        self._enter(State.PREFLIGHT)
        try:
            self.stop.check("the scan")
            summary = self.preflight()
            if not self._ask(f"Start motion? {summary.text()}"):
                raise OperatorDeclined("operator declined motion: nothing moved, nothing exposed")
        except BaseException:
            self._shutdown()
            raise
        with self.stop.guarding(self._stop_devices) as guard, self.stop.deferring():
            try:
                self._enter(State.APPROACH)
                self.stop.check("PREP")
                self.backend.generator.prepare(self.settings.warmup_timeout_s)
                self._stream("approach")
                question = f"Arms at the scan start. Expose {summary.views_to_acquire} views?"
                if not self._ask(question):
                    raise OperatorDeclined("operator declined exposure")
                self._enter(State.ACQUIRE)
                self._stream("scan", acquire=True)
                self._enter(State.RETREAT)
                self._stream("retreat")
            except BaseException as err:  # the operator's stop included: X-ray off, arms stop
                guard.acknowledge()
                self._safe(err)
        try:  # assembling the stacks can fail too (a full disk): the devices are released
            self.store.finish()
            self._enter(State.DONE)
        finally:
            self._shutdown()

    def _ask(self, question: str) -> bool:
        """The operator's answer; a stop signal while waiting for it ends the wait."""
        with self.stop.interrupting():
            return self.confirm(question)

    def preflight(self) -> Preflight:
        """Check plan, dose, devices and start pose; raises PreflightError naming the problem."""
        plan, model = self.plan, self.model
        n = len(plan.view_times_s)
        if n != self.protocol.orbit.views:
            raise PreflightError(f"plan has {n} views, protocol {self.protocol.orbit.views}")
        if plan.min_clearance_mm < plan.clearance_margin_mm:
            raise PreflightError(
                f"plan clearance {plan.min_clearance_mm:.1f} mm < margin "
                f"{plan.clearance_margin_mm:.1f} mm at {plan.min_clearance_at}"
            )
        lower = model.to_units(model.limits.lower)
        upper = model.to_units(model.limits.upper)
        for k, name in enumerate(plan.joint_names):
            lo, hi = plan.q[:, k].min(), plan.q[:, k].max()
            if lo < lower[k] - 1e-6 or hi > upper[k] + 1e-6:
                raise PreflightError(
                    f"joint {name} spans [{lo:.2f}, {hi:.2f}], outside its limits "
                    f"[{lower[k]:.2f}, {upper[k]:.2f}]"
                )
        todo = [k for k in range(n) if k not in self.store.stored]
        dose = n * self.technique.mas
        if dose > self.protocol.dose_limit_mas + 1e-9:
            raise PreflightError(
                f"scan dose {dose:.1f} mAs ({n} views x {self.technique.mas:.3f} mAs) exceeds "
                f"the protocol limit of {self.protocol.dose_limit_mas:.1f} mAs"
            )
        timeout = self.settings.device_timeout_s
        b = self.backend
        for device in (*b.groups, b.generator, b.detector):
            device.connect(timeout)
        if (b.detector.rows, b.detector.cols) != (self.panel.rows, self.panel.cols):
            raise PreflightError(
                f"detector reads {b.detector.rows}x{b.detector.cols} pixels, protocol asks "
                f"{self.panel.rows}x{self.panel.cols}"
            )
        self._check_maps()
        b.generator.set_technique(self.technique, timeout)
        status = b.generator.status(timeout)
        if not status.interlocks_closed:
            opened = [k for k, closed in status.interlocks.items() if not closed]
            raise PreflightError(f"interlocks open: {opened or 'none reported'}")
        if status.fault:
            raise PreflightError(f"generator fault: {status.fault}")
        q_now = self._read_q()
        error = np.abs(q_now - plan.q[0])
        worst = int(np.argmax(error))
        if error[worst] > self.settings.start_tolerance:
            raise PreflightError(
                f"joint {plan.joint_names[worst]} is at {q_now[worst]:.2f}, the plan starts at "
                f"{plan.q[0, worst]:.2f} (tolerance {self.settings.start_tolerance}): move the "
                "scanner to the plan's start first (cbct scan --move-to-start, or cbct move "
                "--to start)"
            )
        return Preflight(
            views=n,
            views_to_acquire=len(todo),
            duration_s=float(plan.duration_s),
            dose_mas=len(todo) * self.technique.mas,
            dose_limit_mas=self.protocol.dose_limit_mas,
            min_clearance_mm=plan.min_clearance_mm,
            clearance_margin_mm=plan.clearance_margin_mm,
            technique=self.technique,
        )

    def _check_maps(self) -> None:
        """Refuse maps missing, of another panel or mode, or made at another kV."""
        maps, detector = self.maps, self.backend.detector
        if maps is None:
            raise PreflightError(
                f"no offset/gain/defect maps for panel {detector.serial!r} in mode "
                f"{detector.mode!r}: run `cbct detector-calibrate` first"
            )
        if (maps.serial, maps.mode) != (detector.serial, detector.mode):
            raise PreflightError(
                f"detector maps are of panel {maps.serial!r} in mode {maps.mode!r}; the panel is "
                f"{detector.serial!r} in mode {detector.mode!r}"
            )
        if abs(maps.kv - self.technique.kv) > 0.5:
            raise PreflightError(
                f"detector maps were made at {maps.kv:g} kV, the protocol exposes at "
                f"{self.technique.kv:g} kV: calibrate the panel at the protocol's kV"
            )
        self._corrector = Corrector(maps)

    # -- motion -------------------------------------------------------------------------

    def _read_q(self) -> np.ndarray:
        return measured_joints(self.backend, self.settings.device_timeout_s)

    def _stream(self, phase: str, acquire: bool = False) -> None:
        """Stream the plan's ``phase`` to the groups in time; acquire the views in it."""
        plan = self.plan
        t0, t1 = plan.phases[phase]
        inside = (plan.t_s >= t0 - 1e-9) & (plan.t_s <= t1 + 1e-9)
        times, qs = list(plan.t_s[inside]), list(plan.q[inside])
        events: list[tuple[float, np.ndarray, int | None]] = [
            (t, q, None) for t, q in zip(times, qs, strict=True)
        ]
        if acquire:
            events += [(float(t), plan.view_q[k], k) for k, t in enumerate(plan.view_times_s)]
            events.sort(key=lambda e: (e[0], e[2] is not None))
        clock = self.backend.clock
        origin = clock.now() - events[0][0]
        previous = events[0][0]
        for t, q, view in events:
            dt = max(t - previous, 0.0)
            if dt > 0:
                with self.stop.commanding(f"{phase} set-point at {t:.3f} s"):
                    for group, idx in zip(self.backend.groups, GROUP_SLICES, strict=True):
                        group.servo(q[idx], dt)
                clock.sleep_until(origin + t)
            previous = t
            if view is not None and view not in self.store.stored:
                self._acquire(view)
            # work that overran its sample (a view's exposure, read-out and storage on a wall
            # clock) pauses the plan where it is instead of bursting set-points to catch up
            origin = max(origin, clock.now() - t)
        self._finish_storing()  # the last views
        self._report_stored()
        self._release_reserved()  # none is left after the last view; nothing on the way out

    def _acquire(self, k: int) -> None:
        """One view: pose check, interlock check, its files' disk space reserved, expose,
        read, reserve the next view's space, start storing it.

        The storage of the views before it (their files' writes and fsyncs) runs while the plan
        streams on to this view, its pose is checked and its pulse fires: before the interlock
        check and the pulse, all but :data:`VIEWS_STORING_AT_A_PULSE` of them are waited for,
        and a failed one stops the scan; the stored views are handed on after the pulse."""
        b, timeout = self.backend, self.settings.device_timeout_s
        planned = self.plan.achieved[k]  # the view the plan's joints realise
        q, realised = self._settled(k, planned)
        t_reading = b.clock.now()
        self._finish_storing(VIEWS_STORING_AT_A_PULSE)  # the views before on disk first
        status = b.generator.status(timeout)
        if not status.interlocks_closed:
            opened = [name for name, closed in status.interlocks.items() if not closed]
            raise DeviceError(f"view {k}: interlock open ({', '.join(opened)}): not exposing")
        if not status.ready or status.fault:
            raise DeviceError(f"view {k}: generator not ready ({status.fault or 'not prepared'})")
        reserving = self._reserved.get(k)
        if reserving is None or reserving.exception() is not None:  # not made, or refused
            self._reserved[k] = _RESERVER.submit(self.store.reserve, k)
        self._reserved[k].result()  # no dose for a view that cannot be stored
        self.store.check_room(k, reserved=True)  # nor on a disk filled since the reservation
        b.detector.arm(timeout)
        exposure = b.generator.expose(timeout, permit=lambda: self.stop.check(f"view {k}: EXP"))
        self._reserve_next(k)  # while the panel reads out
        self._report_stored()  # handed on while the panel reads out, not amid the requests
        frame = b.detector.read_frame(timeout)
        used = exposure.technique
        line_integrals = self._corrector.line_integrals(frame.counts, used.kv, used.mas)
        record = ViewRecord(
            view=k,
            planned_time_s=float(self.plan.view_times_s[k]),
            clock_s=t_reading,
            frame_clock_s=float(frame.t_s),
            q=q,
            matrix=realised.matrix,
            source_mm=realised.source_mm,
            kv=exposure.technique.kv,
            ma=exposure.technique.ma,
            ms=exposure.technique.ms,
            exposure_sequence=exposure.sequence,
            true_matrix=self.truth(),
            true_poses=self.true_poses(),
        )
        raw = np.asarray(frame.counts, dtype=np.float32)  # exact for 16-bit counts
        pending = self.store.start_put(record, line_integrals, raw)
        self._storing.append((pending, line_integrals))
        del self._reserved[k]  # its files are being written

    def _reserve_next(self, k: int) -> None:
        """Start reserving the space of the view acquired after ``k`` (on :data:`_RESERVER`,
        while view ``k``'s panel reads out): creating its three files took 1-3 ms in a busy
        scan (ext4's inode allocation, 0.9 ms of it CPU), off the exposure loop here. A refusal
        (a full disk) is not an error yet: that view's turn tries again before its pulse and
        stops the scan if the disk still cannot take it."""
        n = len(self.plan.view_times_s)
        later = (j for j in range(k + 1, n) if j not in self.store.records)
        j = next(later, None)
        if j is not None and j not in self._reserved:
            self._reserved[j] = _RESERVER.submit(self.store.reserve, j)

    def _release_reserved(self) -> None:
        """Release the space of views reserved and not acquired (waiting for a reservation
        under way)."""
        while self._reserved:
            reserving = self._reserved.popitem()[1]
            if reserving.exception() is None:
                reserving.result().release()

    def _finish_storing(self, keep: int = 0) -> None:
        """Wait until all but the ``keep`` newest views being stored are on disk (then they are
        stored, to be handed on by :meth:`_report_stored`); raises StudyError naming the first
        view that could not be stored (also one of the ``keep`` newest whose storage has
        failed already), which is then no longer being stored."""
        while self._storing:
            pending, image = self._storing[0]
            if len(self._storing) <= keep and not pending.failed:
                return
            try:
                pending.wait()
            except Exception as err:
                self._storing.popleft()
                k = pending.record.view
                raise StudyError(f"view {k} could not be stored: {err}") from err
            self._storing.popleft()
            self._unreported.append((pending.record, image))

    def _report_stored(self) -> None:
        """Hand the views stored since the last call on (on_view: the recording, a live
        reconstruction) and report the progress."""
        while self._unreported:
            record, image = self._unreported.pop(0)
            self.on_view(record, image)
            self.progress(
                Progress(
                    len(self.store.stored) - len(self._unreported),
                    len(self.plan.view_times_s),
                    self.store.dose_mas,
                    time.perf_counter() - self._started,
                    self.state,
                )
            )

    def _settled(self, k: int, planned: View) -> tuple[np.ndarray, View]:
        """The measured joints and realised view once they are within tolerance of view ``k``.

        The view's set-point has been sent; arms held up (e.g. a wall clock that stalled) get
        up to ``settle_s`` to reach it while the stream waits, then the view is refused."""
        clock = self.backend.clock
        deadline = clock.now() + self.settings.settle_s
        while True:
            self.stop.check(f"view {k}")
            q = self._read_q()
            realised = view_at(self.model, q, self.panel)
            off = self._pose_error(k, realised, planned)
            if off is None:
                return q, realised
            if clock.now() >= deadline:
                raise DeviceError(off)
            clock.sleep_until(clock.now() + SETTLE_POLL_S)

    def _pose_error(self, k: int, realised: View, planned: View) -> str | None:
        ds = float(np.linalg.norm(realised.source_mm - planned.source_mm))
        dd = float(np.linalg.norm(realised.detector_center_mm - planned.detector_center_mm))
        angle = float(np.degrees(np.arccos(np.clip(realised.normal @ planned.normal, -1, 1))))
        tol_mm, tol_deg = self.settings.pose_tolerance_mm, self.settings.pose_tolerance_deg
        if ds > tol_mm or dd > tol_mm or angle > tol_deg:
            return (
                f"view {k}: arms off pose (source {ds:.2f} mm, detector {dd:.2f} mm, panel "
                f"{angle:.2f} deg; tolerance {tol_mm} mm, {tol_deg} deg): not exposing"
            )
        return None

    # -- transitions and SAFE -----------------------------------------------------------

    def _enter(self, state: State) -> None:
        self.state = state
        self.transitions.append((time.perf_counter() - self._started, state))

    def _safe(self, err: BaseException) -> None:
        failed_in = self.state
        self._enter(State.SAFE)
        problems = self._stop_devices()
        reason = self.stop.explain(err)
        if problems:
            reason += "; " + "; ".join(problems)
        while self._storing:  # the data so far is flushed: the last views' files
            try:
                self._finish_storing()
            except Exception as store_err:  # e.g. the disk is full: it was not stored
                reason += f"; {store_err}"
        self._release_reserved()  # views not acquired after all
        try:
            self._report_stored()
        except Exception as report_err:  # e.g. the recording failed: the view is stored
            reason += f"; {report_err}"
        try:
            self.store.mark_incomplete(reason, failed_in.value)
        except Exception as mark_err:  # e.g. the disk is full: still release the devices
            reason += f"; the study could not be marked incomplete: {mark_err}"
        self._shutdown()
        stored, views = len(self.store.stored), len(self.plan.view_times_s)
        raise ScanFault(failed_in, reason, stored, views) from err

    def _stop_devices(self) -> list[str]:
        """X-ray off, then every joint group stops (:func:`stop_safely`): SAFE's first step,
        also the watchdog's action on a stop the loop has not taken in hand."""
        return stop_safely(self.backend, self.settings.device_timeout_s)

    def _shutdown(self) -> None:
        if not self.close_backend:
            return
        try:
            self.backend.close()
        except Exception:  # closing after SAFE must not mask the fault
            pass


def measured_joints(backend: Backend, timeout_s: float) -> np.ndarray:
    """The measured joints of all groups in the plan's order and units (14,); raises
    DeviceError when a group is in a protective stop."""
    q = np.empty(14)
    for group, idx in zip(backend.groups, GROUP_SLICES, strict=True):
        reading = group.state(timeout_s)
        if reading.protective_stop:
            raise DeviceError(f"{group.name}: protective stop")
        q[idx] = reading.q
    return q


def stop_safely(backend: Backend, timeout_s: float) -> list[str]:
    """SAFE's order: X-ray off first (the generator's abort), then every joint group stops,
    all at once, each attempted whatever the others do; returns what failed, in words."""
    problems = []
    try:
        backend.generator.abort(timeout_s)
    except Exception as abort_err:  # still stop the arms; report loudly
        problems.append(f"X-RAY OFF NOT CONFIRMED: {abort_err}")
    # every group at once: one that does not answer (its stop waits for its deadline) must not
    # hold the others up
    stops = [_STOPPERS.submit(group.stop) for group in backend.groups]
    for group, stop in zip(backend.groups, stops, strict=True):
        try:
            stop.result()
        except Exception as stop_err:
            problems.append(f"{group.name} stop failed: {stop_err}")
    return problems

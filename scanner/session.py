"""A scan session into a study folder: what ``cbct scan`` runs.

New study: every input is read and validated first (protocol, scanner, backend, phantom), the
study folder is created with the config snapshot, the scan is planned into ``plan/``, the
backend opened and the state machine run, streaming views into ``scan/`` and a recording.
Resume (``--resume``): the study's own snapshot is used, the plan is made again and must equal
the stored one, stored views are verified against their checksums, and only the views not yet
stored are acquired.
"""

from __future__ import annotations

import shutil
import time
from collections.abc import Callable
from dataclasses import replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Protocol

import numpy as np

from recon.config import ScanProtocol, load_config, load_protocol
from recon.geometry import View
from scanner.corrections import MapsError, PanelMaps, find_maps
from scanner.hardware import Backend, Technique, close_quietly
from scanner.inputs import SessionInputs, load_backend_spec, subject
from scanner.move import MoveResult, move_scanner
from scanner.registry import Rig, backend_kind
from scanner.scan import PreflightError, ScanFault, ScanRun, ScanSettings
from scanner.scan import Progress as ScanProgress
from scanner.scan_recording import ScanRecorder
from scanner.stop import StopRequest, stop_signals
from scanner.storage import ScanStore, ViewRecord
from scanner.study_folder import MANIFEST, Study, StudyError
from trajectories.config import ScannerConfig
from trajectories.model import ScannerModel
from trajectories.move import park_pose
from trajectories.plan import Plan, plan_scan
from trajectories.plan_recording import record_plan

Say = Callable[[str], None]


class ViewSink(Protocol):
    """Takes every view of a scan as it is stored (e.g. a reconstruction during acquisition).

    ``start`` is called once the store is open, before anything moves: the views already
    stored (a resumed scan) are the sink's to read from it. ``view`` runs in the exposure loop
    after each view is stored, so it must return at once (queue the work)."""

    def start(self, store: ScanStore) -> None: ...

    def view(self, record: ViewRecord, image: np.ndarray) -> None: ...


def plan_stage(study: Study, model: ScannerModel, protocol: ScanProtocol, say: Say) -> Plan:
    """The study's plan: made and saved (with its rerun recording) the first time; made again
    and checked against the stored one afterwards."""
    say("planning the scan (IK, clearance, timing)")
    plan = plan_scan(model, protocol)
    folder = study.path / "plan"
    if study.stage("plan").get("status") == "complete":
        if altered := study.verify("plan/"):  # before reading them: np.load trusts the file
            raise StudyError(f"{folder}: files altered: {altered}")
        stored = np.load(folder / "trajectory.npz")
        if stored["q"].shape != plan.q.shape or not np.allclose(stored["q"], plan.q, atol=1e-9):
            raise StudyError(
                f"{folder}: the plan made again differs from the stored one (software or "
                "config changed since): refusing to continue on a different motion"
            )
        return plan
    _save_plan(study, plan, model)
    return plan


def _save_plan(study: Study, plan: Plan, model: ScannerModel) -> None:
    folder = study.path / "plan"
    if folder.exists():  # an interrupted earlier attempt: derived data, made again
        shutil.rmtree(folder)
    plan.save(folder)
    record_plan(plan, model, folder / "recording.rrd")
    study.adopt("plan")
    study.mark("plan", "complete", **plan.summary())


def plan_study(
    protocol_path: Path,
    study_path: Path,
    scanner_path: Path,
    progress: Callable[[int, int], None] | None = None,
) -> Plan:
    """``cbct plan``: plan a protocol into a new study folder, which ``cbct scan --study``
    then scans (the scan plans again and refuses a plan that differs).

    Args:
        protocol_path: Scan protocol YAML.
        study_path: The new study folder (or an empty one).
        scanner_path: Scanner hardware YAML.
        progress: Called with (views solved, views in all) during inverse kinematics.
    """
    protocol = load_protocol(protocol_path)
    model = ScannerModel(load_config(scanner_path, ScannerConfig))
    plan = plan_scan(model, protocol, progress=progress)  # nothing is written unless it holds
    _save_plan(Study.create(study_path, {}), plan, model)
    return plan


def run_session(
    study_path: Path,
    inputs: SessionInputs | None,
    *,
    resume: bool = False,
    backend_override: object | None = None,
    confirm: Callable[[str], bool] = lambda _q: True,
    progress: Callable[[ScanProgress], None] = lambda _p: None,
    say: Say = lambda _m: None,
    settings: ScanSettings | None = None,
    sink: ViewSink | None = None,
    move_to_start: bool = False,
    park: bool = False,
) -> Study:
    """Plan and scan into ``study_path`` (new), or continue it (``resume``; the backend's
    config may be given again, e.g. new addresses, or a simulation without the fault).
    ``move_to_start`` and ``park`` as in :func:`scan_stage`."""
    if resume:
        study = Study.open(study_path)
    else:
        if inputs is None:
            raise ValueError("a new study needs its inputs")
        if (Path(study_path) / MANIFEST).is_file():  # a study made by cbct plan: scan it
            study = Study.open(study_path)
            if study.manifest["config"] or set(study.manifest["stages"]) != {"plan"}:
                raise StudyError(
                    f"{study_path} is a study already scanned (or started): continue it with "
                    "--resume, or choose a new folder"
                )
        else:
            study = Study.create(study_path, {})
    scan_stage(
        study,
        None if resume else inputs,
        backend_override=backend_override,
        confirm=confirm,
        progress=progress,
        say=say,
        settings=settings,
        sink=sink,
        move_to_start=move_to_start,
        park=park,
    )
    return study


def scan_stage(
    study: Study,
    inputs: SessionInputs | None,
    stage: str = "scan",
    *,
    backend_override: object | None = None,
    confirm: Callable[[str], bool] = lambda _q: True,
    progress: Callable[[ScanProgress], None] = lambda _p: None,
    say: Say = lambda _m: None,
    settings: ScanSettings | None = None,
    sink: ViewSink | None = None,
    move_to_start: bool = False,
    park: bool = False,
    stop: StopRequest | None = None,
) -> None:
    """Scan ``stage`` (``scan`` or ``calibration_scan``) of an open study: with new
    ``inputs`` (recorded as the stage's config snapshot), or, when ``inputs`` is None,
    continue it with its snapshot (and ``backend_override`` if given). ``sink`` takes every
    view as it is stored (:class:`ViewSink`).

    ``move_to_start``: first move the scanner from where it stands to the plan's start
    (:func:`scanner.move.move_scanner`, confirmed through ``confirm``). ``park``: once the scan
    is done, or once a fault has reached SAFE, move it to park the same way; a park that is
    refused or fails is said and recorded in ``study.json`` (``moves``), and the scan's own
    outcome stands; after the operator's stop nothing is parked.

    While the devices are open the stop signals (Ctrl-C, SIGTERM, SIGHUP, SIGQUIT) set
    ``stop`` (a new request when None; :func:`scanner.stop.stop_signals`). Every command sent
    to the generator is logged with its time to ``<scan folder>/generator_commands-N.csv``."""
    if study.stage(stage).get("status") == "complete":
        raise StudyError(f"{study.path}: {stage} is complete; nothing to resume")
    configs = study.manifest["config"]
    if inputs is None:
        if stage not in configs:
            raise StudyError(f"{study.path}: no {stage} was started; nothing to resume")
        inputs = SessionInputs.from_snapshot(configs[stage])
        if backend_override is not None:
            if type(backend_override) is not type(inputs.backend):
                raise StudyError(
                    f"{study.path} was scanned on the {inputs.backend_kind} backend; the resume "
                    f"config is a {type(backend_override).__name__}"
                )
            inputs = replace(inputs, backend=backend_override)
        else:
            quiet, note = backend_kind(inputs.backend_kind).resumed(inputs.backend)
            if note:
                say(note)
            inputs = replace(inputs, backend=quiet)
    elif stage in configs:
        raise StudyError(f"{study.path}: {stage} was started already; continue it with --resume")
    else:
        configs[stage] = inputs.snapshot()
        study.save()
    model = ScannerModel(inputs.scanner)
    plan = plan_stage(study, model, inputs.protocol, say)
    panel = inputs.panel
    store = ScanStore(study, panel, plan.joint_names, len(plan.view_times_s), plan.achieved, stage)
    if store.stored:
        say(f"{len(store.stored)} views already stored and verified")
    commands: list[tuple[float, str]] = []  # the generator's command log of this session
    rig = Rig(
        model,
        plan.q[0],
        panel,
        inputs.protocol.orbit.sdd_mm,
        subject(inputs, say, plan.scan_duration_s),
        on_generator_sent=lambda body, t_s: commands.append((t_s, body)),
    )
    backend, truth = backend_kind(inputs.backend_kind).open(inputs.backend, rig)
    try:
        maps = panel_maps(inputs, backend, rig, say)
    except BaseException:
        close_quietly(backend)
        raise
    recorder = ScanRecorder(study, plan.joint_names, panel.pixel_pitch_mm, stage)
    on_view = recorder.view
    if sink is not None:
        sink.start(store)

        def on_view(record: ViewRecord, image: np.ndarray) -> None:
            recorder.view(record, image)
            sink.view(record, image)

    settings = settings or ScanSettings()
    stop = stop or StopRequest()
    run = ScanRun(
        backend=backend,
        model=model,
        plan=plan,
        protocol=inputs.protocol,
        store=store,
        settings=settings,
        confirm=confirm,
        progress=progress,
        on_view=on_view,
        truth=truth.view_matrix if truth else lambda: None,
        true_poses=truth.body_poses if truth else lambda: None,
        close_backend=False,
        stop=stop,
        maps=maps,
    )
    sessions = study.manifest.setdefault("sessions", [])
    sessions.append({"stage": stage, "backend": inputs.backend.model_dump(mode="json")})
    study.save()

    def move(goal: np.ndarray, target: str) -> None:
        move_recorded(study, backend, model, goal, target, settings, confirm, say, stop)

    def park_after_scan() -> None:
        if stop.is_set:  # the operator's stop holds: nothing moves again by itself
            say(f"PARK NOT DONE: stopped by {stop.reason}; park with: cbct move --to park")
            return
        try:
            move(park_pose(model), "park")
        except (ValueError, RuntimeError) as err:  # the scan's outcome stands
            say(f"PARK NOT DONE: {err}")

    def finish_records() -> None:
        recorder.close()
        _write_generator_commands(study, store.folder, commands, len(sessions))
        if truth is not None:
            _write_device_events(study, store.folder, truth.events(), len(sessions))

    with stop_signals(stop):
        try:
            if move_to_start:
                move(plan.q[0], "the plan's start")
            say(f"{stage}: acquiring on the {inputs.backend_kind} backend")
            try:
                run.run()
            except ScanFault:  # SAFE reached: X-ray off, arms stopped, the views so far kept
                if park:
                    park_after_scan()
                raise
            if park:
                park_after_scan()
        except BaseException:
            close_quietly(backend)
            try:  # the scan's own failure is the one to report (e.g. a full disk fails both)
                finish_records()
            except Exception as err:
                say(f"the recording and device logs of this session were not finished: {err}")
            raise
        close_quietly(backend)
        finish_records()


def panel_maps(inputs: SessionInputs, backend: Backend, rig: Rig, say: Say) -> PanelMaps:
    """The maps the scan corrects its frames with: from the backend config's
    ``detector_maps`` folder, for the connected panel's serial number and mode (refused when
    older than ``max_map_age_days``); with no folder, made now by the backend kind's
    ``calibrate_panel`` when it has one (the simulated panel's), else refused."""
    spec = inputs.backend
    if spec.detector_maps is not None:
        backend.detector.connect(ScanSettings().device_timeout_s)
        detector = backend.detector
        try:
            maps = find_maps(
                Path(spec.detector_maps), detector.serial, detector.mode, spec.max_map_age_days
            )
        except MapsError as err:
            raise PreflightError(str(err)) from err
        say(f"detector maps of {maps.serial} ({maps.mode}) made {maps.made}")
        return maps
    calibrate = backend_kind(inputs.backend_kind).calibrate_panel
    if calibrate is None:
        raise PreflightError(
            f"the {inputs.backend_kind} backend config names no detector_maps folder: run "
            "`cbct detector-calibrate` and set detector_maps to its output"
        )
    e = inputs.protocol.exposure
    maps = calibrate(spec, rig, Technique(e.tube_kv, e.tube_ma, e.pulse_ms))
    say(
        f"{inputs.backend_kind} panel calibrated: {int(maps.defects.sum())} defective pixels, "
        f"lag {maps.lag:.3f}"
    )
    return maps


def _write_generator_commands(
    study: Study, folder: str, commands: list[tuple[float, str]], session: int
) -> None:
    """Every command this session sent to the X-ray generator, in order, with the time it was
    sent (``monotonic_s``: the host's ``time.monotonic()``, one clock for every process on the
    host; ``utc``): ``<scan folder>/generator_commands-<session>.csv``."""
    to_utc = time.time() - time.monotonic()
    lines = ["monotonic_s,utc,command"] + [
        f"{t:.6f},{datetime.fromtimestamp(t + to_utc, UTC).isoformat(timespec='microseconds')},"
        f"{body}"
        for t, body in commands
    ]
    text = "\n".join(lines) + "\n"
    study.write(
        f"{folder}/generator_commands-{session}.csv",
        lambda p: p.write_text(text, encoding="utf-8"),
    )
    study.save()


def _write_device_events(study: Study, folder: str, events: list, session: int) -> None:
    """The simulator's ordered device log of this session (sequence, virtual time, device,
    event): ``<scan folder>/device_events-<session>.csv``."""
    lines = ["sequence,time_s,device,event"] + [
        f"{seq},{t:.6f},{who},{what}" for seq, t, who, what in events
    ]
    text = "\n".join(lines) + "\n"
    study.write(
        f"{folder}/device_events-{session}.csv", lambda p: p.write_text(text, encoding="utf-8")
    )
    study.save()


def move_recorded(
    study: Study,
    backend: Backend,
    model: ScannerModel,
    goal: np.ndarray,
    target: str,
    settings: ScanSettings,
    confirm: Callable[[str], bool],
    say: Say,
    stop: StopRequest | None = None,
) -> MoveResult:
    """:func:`scanner.move.move_scanner`, its outcome appended to ``study.json``'s ``moves``
    (target, status, the move's summary, the joints reached) whatever it is."""
    entry: dict = {"target": target, "backend": backend.name}
    try:
        result = move_scanner(
            backend, model, goal, target, settings=settings, confirm=confirm, say=say, stop=stop
        )
    except BaseException as err:
        entry.update(status="failed", reason=f"{type(err).__name__}: {err}")
        raise
    else:
        entry.update(
            status="done" if result.move else "already there",
            reached=np.round(result.reached_q, 3).tolist(),
            error=round(result.error, 4),
            **(result.move.summary() if result.move else {}),
        )
        return result
    finally:
        study.manifest.setdefault("moves", []).append(entry)
        study.save()


def move_session(
    study_path: Path,
    to: str,
    *,
    stage: str = "scan",
    backend_config: Path | None = None,
    confirm: Callable[[str], bool] = lambda _q: True,
    say: Say = lambda _m: None,
    settings: ScanSettings | None = None,
) -> MoveResult:
    """Move the scanner of a study's ``stage`` to ``to`` ("start": its plan's start, made again
    and checked against the stored plan; "park": :func:`trajectories.move.park_pose`) on the
    stage's backend (``backend_config``: that backend's config given again, e.g. new
    addresses)."""
    if to not in ("start", "park"):
        raise ValueError(f"move target must be 'start' or 'park', got {to!r}")
    study = Study.open(study_path)
    configs = study.manifest["config"]
    if stage not in configs:
        raise StudyError(
            f"{study.path}: no {stage} was started, so there is no plan to move to: start it "
            "with cbct scan --move-to-start"
        )
    inputs = SessionInputs.from_snapshot(configs[stage])
    if backend_config is not None:
        inputs = replace(inputs, backend=load_backend_spec(inputs.backend_kind, backend_config))
    model = ScannerModel(inputs.scanner)
    if to == "start":
        goal, target = plan_stage(study, model, inputs.protocol, say).q[0], "the plan's start"
    else:
        goal, target = park_pose(model), "park"
    rig = Rig(model, goal, inputs.panel, inputs.protocol.orbit.sdd_mm, _no_exposure)
    backend, _ = backend_kind(inputs.backend_kind).open(inputs.backend, rig)
    stop = StopRequest()
    with stop_signals(stop):
        try:
            return move_recorded(
                study, backend, model, goal, target, settings or ScanSettings(), confirm, say, stop
            )
        finally:
            close_quietly(backend)


def _no_exposure(view: View, t_s: float = 0.0) -> np.ndarray:
    raise RuntimeError("a move never exposes: the panel has nothing to image")

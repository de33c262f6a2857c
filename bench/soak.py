"""Benchmark: a soak of consecutive simulated scans with random faults, each resumed to the end.

Each of ``--scans`` scans (``--views`` views of 64^2 over a 90-degree arc, the knee phantom at
2 mm; the scanning process is ``cbct scan``, a child process) draws one or two faults, each at
a random view of its own session; after each fault the scan is continued with ``cbct scan
--resume``, and once its faults are spent a last resume completes it. The faults:

- ``protective_stop``, ``generator_timeout``, ``dropped_frame``, ``interlock``: the simulated
  backend's hooks (``sim.backend.SimFaults``);
- ``camera_gone``: with ``--gige-interface``, the simulated scans' panel is served as a GigE
  Vision camera (``sim.gige_panel``) and read by the GigE Vision driver; this fault SIGKILLs
  the camera's process when a view's frame is asked for (``camera_gone_at_view``);
- ``controller_silent``: such a scan runs on the UR backend against two fake UR controllers
  (``sim.ur_controller``), the stage and the generator served over ptys by this process; one
  controller stops answering at a random set-point (``--silent-after-servo``). The scan's
  other fault, if any, comes from the same devices' hooks (a fake's protective stop, the mock
  generator's timeout and interlock; the UR backend's panel has no dropped-frame hook);
- ``sigint``, ``sigterm``, ``sighup``, ``sigquit`` (the stop signals: Ctrl-C, a service
  manager's stop, a closed terminal, Ctrl-\\) and ``sigkill``: this process signals the
  scanning process once the study holds a random number of views; SIGKILL waits for a view's
  temporary file, to land mid-write, and kills the whole process group;
- ``disk_full``: the study lives on a tmpfs of its own, which this process fills once the
  study holds a random number of views and empties after the session (without permission to
  mount: the child's RLIMIT_FSIZE set to 0 with prlimit; no timing then).

Measured (printed as one JSON object):

- ``views_lost``: views ever reported stored (a view's record, or study.json's checksums, after
  any session) that are missing or changed in the finished study;
- ``corrupt_files``: files of the finished study failing study.json's sha256, and projections
  (views and stacks) or JSON files that do not read (recon.io); ``stray_temp_files`` apart;
- ``x_ray_on_after_fault``: pulses the generator switched on after a fault and before its
  ABORT (the device event log; for a full disk, after the fill ended); after a stop signal,
  the pulses commanded after it: their ``EXP`` was sent (the session's generator command log,
  ``scan/generator_commands-N.csv``, times each command as the scanning process sent it)
  after ``os.kill`` had returned, i.e. once the signal was pending in the process;
- ``exp_after_stop``: ``EXP`` commands sent after a stop signal, whether or not the generator
  fired (after its ABORT it refuses); ``pulses_in_flight_at_stop``: pulses whose ``EXP`` went
  out before the signal and whose X-ray came on after it (not counted above);
  ``pulses_in_flight_at_camera_gone``: a camera that dies while a frame's window is open
  leaves that frame's pulse to fire (nothing can know before the frame timeout, from which
  on pulses count as after the fault); ``max_kill_call_ms``: the longest ``os.kill`` call,
  from the time before it (time to SAFE runs from there) to its return (commands are judged
  against that);
- ``max_time_to_safe_ms``: from a fault to X-ray off (the generator's ABORT) and every joint
  group stopped (a protective stop stops its arm; a silent controller cannot be stopped and is
  left out), over the faults the software is told of at once; faults found by a deadline
  have their own bounds: a generator that does not answer (the device timeout), a silent
  controller (``silence_s`` + one set-point period) and a full disk on the UR backend (the
  next view), ``time_to_safe_bound_ms``. SIGKILL has none (nothing is left to act).

Each scan runs on a backend drawn from ``--backends`` (a ``controller_silent`` scan on the UR
backend, a ``dropped_frame`` one on the simulated backend, whose hook it is).

Usage: ``python bench/soak.py [--scans 20] [--seed 0] [--views 24] [--kinds a,b,...]
[--backends sim,ur] [--gige-interface 127.0.0.5]`` (without ``--gige-interface`` the
``camera_gone`` kind is left out).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import resource
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.append(str(ROOT / "bench"))  # measures; after the packages, never before

from measures import cpu_model  # noqa: E402

from recon.config import ScanProtocol, load_config  # noqa: E402
from recon.io import read_projections  # noqa: E402
from scanner.detector_calibration import calibrate_session  # noqa: E402
from scanner.inputs import read_inputs  # noqa: E402
from scanner.scan import ScanSettings  # noqa: E402
from scanner.study_folder import Study, sha256  # noqa: E402
from scanner.ur import SILENCE_S  # noqa: E402
from sim.generator import MockGenerator  # noqa: E402
from sim.stage import MockStage  # noqa: E402
from sim.ur_controller import FakeURController  # noqa: E402
from study.simulator import SIM_GIGE_FRAME_TIMEOUT_S  # noqa: E402
from trajectories.config import ScannerConfig  # noqa: E402
from trajectories.model import ScannerModel  # noqa: E402
from trajectories.plan import SAMPLE_DT_S, plan_scan  # noqa: E402

CONFIGS = ROOT / "configs"
KINDS = (
    "protective_stop",
    "generator_timeout",
    "dropped_frame",
    "interlock",
    "controller_silent",
    "sigint",
    "sigterm",
    "sighup",
    "sigquit",
    "sigkill",
    "disk_full",
    "camera_gone",
)
BACKENDS = ("sim", "ur")
SIM_HOOKS = {
    "protective_stop": "protective_stop_at_view",
    "generator_timeout": "generator_timeout_at_view",
    "dropped_frame": "dropped_frame_at_view",
    "interlock": "interlock_open_at_view",
    "camera_gone": "camera_gone_at_view",
}
SIM_ONLY = ("dropped_frame", "camera_gone")
"""Faults of the simulated backend's own hooks."""
STOP_SIGNALS = {
    "sigint": signal.SIGINT,
    "sigterm": signal.SIGTERM,
    "sighup": signal.SIGHUP,
    "sigquit": signal.SIGQUIT,
}
PROCESS_FAULTS = (*STOP_SIGNALS, "sigkill", "disk_full")
SIGNALLED_BOUND_MS = 100.0
"""Fault to SAFE for a fault the software is told of (an error reply, an exception, a signal)."""
DEVICE_TIMEOUT_S = ScanSettings().device_timeout_s
BOUNDS_MS = {
    "generator_timeout": DEVICE_TIMEOUT_S * 1e3 + SIGNALLED_BOUND_MS,
    "controller_silent": (SILENCE_S + SAMPLE_DT_S) * 1e3 + SIGNALLED_BOUND_MS,
    "camera_gone": SIM_GIGE_FRAME_TIMEOUT_S * 1e3 + SIGNALLED_BOUND_MS,
}
"""Faults found by a deadline: the deadline (a dead GigE Vision camera: the frame timeout), then
as fast as a signalled fault. A full disk on
the UR backend (wall clock) is found when the next view is about to be exposed (nothing is
written between views): the plan's longest gap between views, then as fast
(:meth:`Soak.bound_ms`); on the simulated backend's virtual clock views follow at once."""
UR_HOSTS = ("127.0.0.61", "127.0.0.62")
"""Addresses of the soak's fake UR controllers (not the test suite's)."""
GROUPS = ("stage", "source_arm", "detector_arm")
SESSION_TIMEOUT_S = 240.0
"""A session still running after this is a hang: killed and counted."""
TMPFS_SIZE = "32m"
"""A study of the soak takes about 3 MB."""
HEADROOM_BYTES = 8 << 20
"""Free space a disk-full scan's session starts with (the rest is taken by a ballast file),
so that filling it at the fault takes a few milliseconds."""


def protocol_data(views: int) -> dict:
    """The demo knee protocol read out 8x8 binned (64^2), ``views`` views over 90 degrees."""
    data = yaml.safe_load((CONFIGS / "protocols" / "demo_knee.yaml").read_text(encoding="utf-8"))
    data["detector"] = {"rows": 64, "cols": 64, "pixel_pitch_mm": 9.6}
    data["orbit"].update(views=views, arc_deg=90, z_travel_mm=20)
    data["name"] = f"soak_{views}"
    ScanProtocol.model_validate(data)
    return data


@dataclass
class FaultRecord:
    """One drawn fault and what it led to."""

    kind: str
    scan: int
    session: int
    backend: str
    view: int
    injected_s: float | None = None
    certain_s: float | None = None  # when the fault surely holds (a filled disk), else injected_s
    time_to_safe_ms: float | None = None
    xray_after: int = 0
    exp_after: int = 0  # EXP commands sent after a stop signal
    in_flight: int = 0  # pulses on after a stop signal whose EXP went out before it, or
    # after a camera died before its frame timeout
    note: str = ""


@dataclass
class Totals:
    faults: list[FaultRecord] = field(default_factory=list)
    views_lost: int = 0
    corrupt_files: int = 0
    stray_temp_files: int = 0
    resumes: int = 0
    hangs: int = 0
    complete: int = 0
    problems: list[str] = field(default_factory=list)


# -- the study on disk ---------------------------------------------------------------------------


def stored_views(study: Path) -> dict[str, str]:
    """Files of the views reported stored now: each view's record and the images it names,
    and every view file study.json holds a checksum of; relpath -> sha256."""
    out: dict[str, str] = {}
    views = study / "scan" / "views"
    if views.is_dir():
        for record in views.glob("view_*.json"):
            try:
                data = json.loads(record.read_text(encoding="utf-8"))
            except (OSError, json.JSONDecodeError):
                continue  # judged at the end (corrupt_files)
            out[record.relative_to(study).as_posix()] = sha256(record)
            out.update(data.get("files", {}))
    with contextlib.suppress(OSError, json.JSONDecodeError):
        manifest = json.loads((study / "study.json").read_text(encoding="utf-8"))
        out.update({k: v for k, v in manifest["files"].items() if k.startswith("scan/views/")})
    return out


def scan_complete(study: Path) -> bool:
    try:
        return Study.open(study).stage("scan").get("status") == "complete"
    except Exception:  # no study yet, or its manifest unreadable (judged at the end)
        return False


def count_views(study: Path) -> int:
    """The view records in place in the study's scan: a view's files reserved before its
    pulse, or left half-written by a kill (``.view_0004.tmp.json``), are not a stored view."""
    try:
        return sum(
            1
            for e in os.scandir(study / "scan" / "views")
            if e.name.endswith(".json") and not e.name.startswith(".")
        )
    except FileNotFoundError:
        return 0


def judge_study(study: Path, ledger: dict[str, str], totals: Totals) -> bool:
    """Check the finished study against the ledger and its manifest; True when complete."""
    done = Study.open(study)
    complete = done.stage("scan").get("status") == "complete"
    for relpath, digest in ledger.items():
        path = study / relpath
        if not path.is_file() or sha256(path) != digest:
            totals.views_lost += 1
            totals.problems.append(f"{study}: {relpath} lost or changed")
    bad = done.verify()
    totals.problems += [f"{study}: {relpath} fails its sha256" for relpath in bad]
    for relpath in done.manifest["files"]:
        path = study / relpath
        if relpath in bad or not path.is_file():
            continue
        try:
            if path.suffix == ".mha" and relpath.startswith("scan/"):
                read_projections(path)
            elif path.suffix == ".json":
                json.loads(path.read_text(encoding="utf-8"))
        except Exception as err:
            bad.append(relpath)
            totals.problems.append(f"{study}: {relpath} unreadable: {err}")
    totals.corrupt_files += len(bad)
    totals.stray_temp_files += sum(1 for p in study.rglob(".*") if p.is_file())
    return complete


# -- faults in this process ----------------------------------------------------------------------


def wait_for_views(study: Path, views: int, process: subprocess.Popen) -> bool:
    """Wait until the study holds ``views`` views; False when the process ended first."""
    while count_views(study) < views:
        if process.poll() is not None:
            return False
        time.sleep(0.001)
    return True


def kill_mid_write(study: Path, process: subprocess.Popen) -> str:
    """SIGKILL the process group as soon as a view's temporary file exists (within 0.5 s)."""
    folder = study / "scan" / "views"
    deadline = time.monotonic() + 0.5
    seen = False
    while time.monotonic() < deadline and not seen:
        with contextlib.suppress(FileNotFoundError):
            seen = any(e.name.startswith(".") for e in os.scandir(folder))
    os.killpg(process.pid, signal.SIGKILL)
    return "mid-write" if seen else "between writes"


def fill_disk(folder: Path, name: str, leave_bytes: int = 0) -> Path:
    """Allocate a file ``name`` in ``folder`` until its filesystem has at most ``leave_bytes``
    free (fallocate: no data written, so a full fill takes milliseconds); its path."""
    path = folder / name
    fd = os.open(path, os.O_WRONLY | os.O_CREAT, 0o644)
    try:
        size = os.fstat(fd).st_size
        for step in (1 << 20, 1 << 12):
            while True:
                stat = os.statvfs(folder)
                if stat.f_bavail * stat.f_frsize < leave_bytes + step:
                    break
                try:
                    os.posix_fallocate(fd, size, step)
                except OSError:
                    break
                size += step
    finally:
        os.close(fd)
    return path


def mount_tmpfs(folder: Path) -> bool:
    folder.mkdir(parents=True, exist_ok=True)
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={TMPFS_SIZE}", "tmpfs", str(folder)],
        capture_output=True,
        check=False,
    )
    return done.returncode == 0


# -- device logs ---------------------------------------------------------------------------------

Event = tuple[float, str, str]
"""(time.monotonic(), device, event)."""


def read_sim_events(path: Path) -> list[Event]:
    events = []
    if path.is_file():
        for line in path.read_text(encoding="utf-8").splitlines():
            _, _, wall, who, what = line.split(",", 4)
            events.append((float(wall), who, what))
    return events


def injection_time(kind: str, events: list[Event]) -> float | None:
    """When a device hook fired, from the device log."""
    marks = {
        "protective_stop": lambda who, what: what == "protective_stop",
        "generator_timeout": lambda who, what: who == "generator" and what == "ignored",
        "dropped_frame": lambda who, what: who == "detector" and what.startswith("dropped frame"),
        "interlock": lambda who, what: who == "generator" and what == "interlock",
        "controller_silent": lambda who, what: what == "silent",
        "camera_gone": lambda who, what: who == "detector" and what == "camera gone",
    }[kind]
    times = [t for t, who, what in events if marks(who, what)]
    return min(times) if times else None


def read_commands(path: Path) -> list[tuple[float, str]]:
    """A session's generator command log: (monotonic s when sent, command)."""
    commands = []
    for line in path.read_text(encoding="utf-8").splitlines()[1:]:
        t, _, body = line.split(",", 2)
        commands.append((float(t), body))
    return commands


def new_command_log(study: Path, before: set[Path]) -> Path | None:
    """The generator command log a session wrote (None: it wrote none, e.g. killed)."""
    logs = set((study / "scan").glob("generator_commands-*.csv")) - before
    return max(logs, key=lambda p: int(p.stem.rsplit("-", 1)[1])) if logs else None


def pulses_after_stop(fault: FaultRecord, log: Path | None, events: list[Event]) -> None:
    """Tell the pulses on after a stop signal apart: commanded after it (their EXP sent once
    ``os.kill`` had returned, ``fault.certain_s``: the signal was pending then) or in flight
    (on once ``os.kill`` was called, ``fault.injected_s``, their EXP sent before it returned),
    from the session's generator command ``log``; without one every pulse after the signal
    counts as commanded after it."""
    if fault.injected_s is None or fault.certain_s is None:
        return
    if log is None:
        fault.note += " no generator command log: every pulse after the signal counted;"
        return
    sent = fault.certain_s
    exps_after = [t for t, body in read_commands(log) if body == "EXP" and t >= sent]
    aborts = [
        t
        for t, who, what in events
        if who == "generator" and what == "abort" and t >= fault.injected_s
    ]
    end = aborts[0] if aborts else math.inf
    pulses = [
        t
        for t, who, what in events
        if who == "generator" and what == "xray_on" and fault.injected_s <= t < end
    ]
    # the host sends the next EXP only after the last one's reply: a pulse on after the first
    # EXP sent after the signal is one of those EXPs'
    first = min(exps_after, default=math.inf)
    fault.exp_after = len(exps_after)
    fault.xray_after = sum(1 for t in pulses if t >= first)
    fault.in_flight = len(pulses) - fault.xray_after


def write_timeline(path: Path, fault: FaultRecord, events: list[Event], log: Path | None) -> None:
    """The session's device events and generator commands (``log``) around its fault, in ms
    from the fault, to ``path``: what a fault over its bound is read from."""
    t0 = fault.injected_s
    if t0 is None:
        return
    rows = [(t, who, what) for t, who, what in events]
    if log is not None:
        rows += [(t, "host", f"sent {body}") for t, body in read_commands(log)]
    lines = ["ms_from_fault,device,event"] + [
        f"{(t - t0) * 1e3:.3f},{who},{what}" for t, who, what in sorted(rows) if t >= t0 - 0.5
    ]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def time_to_safe(fault: FaultRecord, events: list[Event], exempt: dict[str, str]) -> None:
    """Fill in the fault's time to SAFE and pulses after it from the session's device log.

    ``exempt``: group -> the event after which it is stopped by its own controller
    ("protective_stop"), or "" for a group that cannot be stopped (silent)."""
    t0 = fault.injected_s
    if t0 is None:
        return
    aborts = [t for t, who, what in events if who == "generator" and what == "abort" and t >= t0]
    pulses = [t for t, who, what in events if who == "generator" and what == "xray_on" and t >= t0]
    certain = t0 if fault.certain_s is None else fault.certain_s
    end = aborts[0] if aborts else math.inf
    fault.xray_after = sum(1 for t in pulses if certain <= t < end)
    if aborts:
        done = [aborts[0]]
    elif not pulses:  # no pulse after the fault (e.g. one after the last view): off all along
        done = [t0]
    else:
        fault.note += " no ABORT after the fault;"
        return
    for group in GROUPS:
        if group in exempt:
            if exempt[group]:
                done += [t for t, who, what in events if who == group and what == exempt[group]][:1]
            continue
        stops = [t for t, who, what in events if who == group and what == "stop" and t >= t0]
        if not stops:
            fault.note += f" {group} never stopped;"
            return
        done.append(stops[0])
    fault.time_to_safe_ms = (max(done) - t0) * 1e3


# -- sessions ------------------------------------------------------------------------------------


class Soak:
    """The soak's state: work folder, protocol, plan (for the UR fakes' start and set-points)."""

    def __init__(
        self,
        work: Path,
        views: int,
        seed: int,
        kinds: tuple[str, ...],
        backends: tuple[str, ...] = BACKENDS,
        gige_interface: str | None = None,
    ) -> None:
        self.work, self.views, self.kinds, self.backends = work, views, kinds, backends
        self.gige_interface = gige_interface
        self.rng = np.random.default_rng(seed)
        self.protocol_path = work / "protocol.yaml"
        data = protocol_data(views)
        self.protocol_path.write_text(yaml.safe_dump(data), encoding="utf-8")
        self.scanner = load_config(CONFIGS / "scanner.yaml", ScannerConfig)
        self.plan = plan_scan(ScannerModel(self.scanner), ScanProtocol.model_validate(data))
        self.totals = Totals()
        self.disk_full_method = "tmpfs"
        self.view_gap_ms = float(np.diff(self.plan.view_times_s).max()) * 1e3

    def panel_maps(self) -> Path:
        """The UR scans' panel maps, made once by ``cbct detector-calibrate``'s code on the
        simulated backend: the UR backend's simulated panel is the same panel (serial, mode)."""
        folder = self.work / "detector-maps"
        if not folder.is_dir():
            inputs = read_inputs(
                self.protocol_path,
                CONFIGS / "scanner.yaml",
                "sim",
                CONFIGS / "backends" / "sim.yaml",
                CONFIGS / "phantoms" / "knee.yaml",
            )
            calibrate_session(inputs, folder, 16)
        return folder

    def bound_ms(self, fault: FaultRecord) -> float:
        """The time to SAFE the fault is held to."""
        if fault.kind == "disk_full" and fault.backend == "ur":
            return self.view_gap_ms + SIGNALLED_BOUND_MS
        if fault.kind == "dropped_frame" and self.gige_interface is not None:
            return BOUNDS_MS["camera_gone"]  # over GigE Vision: found at the frame timeout
        return BOUNDS_MS.get(fault.kind, SIGNALLED_BOUND_MS)

    # one scan ---------------------------------------------------------------------------

    def draw(self) -> list[str]:
        kinds = list(self.rng.choice(self.kinds, size=int(self.rng.integers(1, 3))))
        if "controller_silent" in kinds:  # the UR backend's panel has no such hooks
            kinds = [k for k in kinds if k not in SIM_ONLY] or ["controller_silent"]
        return [str(k) for k in kinds]

    def backend_for(self, kinds: list[str]) -> str:
        """The scan's backend: the UR backend for a silent controller, the simulated one for
        a dropped frame or a camera gone (their hooks), else drawn from ``backends``."""
        if "controller_silent" in kinds:
            return "ur"
        if set(kinds) & set(SIM_ONLY):
            return "sim"
        return str(self.rng.choice(self.backends))

    def scan(self, index: int) -> None:
        kinds = self.draw()
        backend = self.backend_for(kinds)
        folder = self.work / f"scan{index:02d}"
        mounted = "disk_full" in kinds and mount_tmpfs(folder)
        if "disk_full" in kinds and not mounted:
            self.disk_full_method = "rlimit_fsize"
        folder.mkdir(exist_ok=True)
        study = folder / "study"
        ledger: dict[str, str] = {}
        try:
            session = 0
            while True:
                session += 1
                kind = kinds[session - 1] if session <= len(kinds) else None
                # a device fault at a view still to acquire; a process fault once at least
                # one view of the session is stored, before the last one
                remaining = self.views - count_views(study)
                last = remaining - (1 if kind in PROCESS_FAULTS else 0)
                fault = None
                if kind is not None and last >= 1:
                    view = int(self.rng.integers(0, last))
                    fault = FaultRecord(kind, index, session, backend, view)
                self.session(backend, study, folder, session, fault)
                for relpath, digest in stored_views(study).items():
                    ledger.setdefault(relpath, digest)
                if fault is not None:
                    self.totals.faults.append(fault)
                if session > 1:
                    self.totals.resumes += 1
                if scan_complete(study):
                    break
                if session > len(kinds) + 2:
                    self.totals.problems.append(f"scan {index}: not complete after {session}")
                    break
            if judge_study(study, ledger, self.totals):
                self.totals.complete += 1
        finally:
            if mounted:
                subprocess.run(["umount", "-l", str(folder)], check=False)

    def command(self, backend: str, study: Path, config: Path, resume: bool) -> list[str]:
        cmd = [sys.executable, "-m", "study.cli", "scan", "--study", str(study), "--yes"]
        cmd += ["--backend", backend, "--backend-config", str(config), "--recon-voxel-mm", "4"]
        if resume:
            return [*cmd, "--resume"]
        return [*cmd, "--protocol", str(self.protocol_path), "--phantom-voxel-mm", "2"]

    def run_child(
        self, cmd: list[str], study: Path, fault: FaultRecord | None, log: Path
    ) -> int | None:
        """Run one ``cbct scan``, injecting a process-level fault; its exit code (None: hung)."""
        env = dict(os.environ, PYTHONPATH=str(ROOT), NUMBA_NUM_THREADS="1")
        ballast = None
        if fault is not None and fault.kind == "disk_full" and self.disk_full_method == "tmpfs":
            ballast = fill_disk(study.parent, "ballast", HEADROOM_BYTES)
        with open(log, "wb") as out:
            process = subprocess.Popen(
                cmd, cwd=ROOT, env=env, stdout=out, stderr=out, start_new_session=True
            )
            filler = None
            try:
                if fault is not None and fault.kind in PROCESS_FAULTS:
                    target = count_views(study) + fault.view + 1
                    if wait_for_views(study, target, process):
                        if fault.kind in STOP_SIGNALS:  # timed from before the kill; pending
                            fault.injected_s = time.monotonic()  # in the process once it returns
                            os.kill(process.pid, STOP_SIGNALS[fault.kind])
                            fault.certain_s = time.monotonic()
                        elif fault.kind == "sigkill":
                            fault.note = kill_mid_write(study, process)
                            fault.injected_s = time.monotonic()
                        elif self.disk_full_method == "tmpfs":  # timed from the fill's start
                            fault.injected_s = time.monotonic()
                            filler = fill_disk(study.parent, "filler")
                            fault.certain_s = time.monotonic()
                        else:  # the device log cannot be written either: no timing
                            fault.injected_s = time.monotonic()
                            resource.prlimit(process.pid, resource.RLIMIT_FSIZE, (0, 0))
                            fault.note = "rlimit_fsize, no timing"
                try:
                    return process.wait(timeout=SESSION_TIMEOUT_S)
                except subprocess.TimeoutExpired:
                    os.killpg(process.pid, signal.SIGKILL)
                    process.wait()
                    self.totals.hangs += 1
                    self.totals.problems.append(f"{cmd}: hung, killed (log {log})")
                    return None
            finally:
                for path in (filler, ballast):
                    if path is not None:
                        path.unlink()

    def session(
        self, backend: str, study: Path, folder: Path, session: int, fault: FaultRecord | None
    ) -> int | None:
        log = self.work / f"{folder.name}-session{session}.log"  # off the study's disk
        if backend == "sim":
            return self.sim_session(study, folder, session, fault, log)
        return self.ur_session(study, folder, session, fault, log)

    def sim_session(
        self, study: Path, folder: Path, session: int, fault: FaultRecord | None, log: Path
    ) -> int | None:
        events_path = self.work / f"{folder.name}-session{session}-events.csv"
        faults = {}
        if fault is not None and fault.kind in SIM_HOOKS:
            faults[SIM_HOOKS[fault.kind]] = fault.view
        config = folder.parent / f"{folder.name}-session{session}-sim.yaml"
        spec = {"seed": 3, "faults": faults, "event_log": str(events_path)}
        if self.gige_interface is not None:
            spec["panel_gige_interface"] = self.gige_interface
        config.write_text(yaml.safe_dump(spec), encoding="utf-8")
        logs = set((study / "scan").glob("generator_commands-*.csv"))
        code = self.run_child(self.command("sim", study, config, session > 1), study, fault, log)
        if fault is not None and fault.kind != "sigkill":
            events = read_sim_events(events_path)
            if fault.kind in SIM_HOOKS:
                fault.injected_s = injection_time(fault.kind, events)
            if fault.kind == "camera_gone" and fault.injected_s is not None:
                # the camera died with a frame's window open (its trigger answered): that
                # frame's pulse is in flight; nothing can know before the frame timeout
                fault.certain_s = fault.injected_s + SIM_GIGE_FRAME_TIMEOUT_S
                fault.in_flight = sum(
                    fault.injected_s <= t < fault.certain_s
                    for t, who, what in events
                    if who == "generator" and what == "xray_on"
                )
            exempt = {}
            time_to_safe(fault, events, exempt)
            command_log = new_command_log(study, logs)
            if fault.kind in STOP_SIGNALS:
                pulses_after_stop(fault, command_log, events)
            write_timeline(log.with_suffix(".timeline.csv"), fault, events, command_log)
            self._check_injected(fault, code, log)
        return code

    def servo_count(self, view: int) -> int:
        """The set-points streamed to an arm before view ``view`` (approach and scan)."""
        plan = self.plan
        t_view = float(plan.view_times_s[view])
        t0 = plan.phases["approach"][0]
        samples = int(np.count_nonzero((plan.t_s > t0) & (plan.t_s < t_view)))
        return samples + int(np.count_nonzero(plan.view_times_s < t_view))

    def ur_session(
        self, study: Path, folder: Path, session: int, fault: FaultRecord | None, log: Path
    ) -> int | None:
        q0 = self.plan.q[0]
        events: list[Event] = []

        def recorder(device: str) -> Callable[[str, dict], None]:
            return lambda name, _info: events.append((time.monotonic(), device, name))

        kind = fault.kind if fault is not None else None
        done = count_views(study)
        target = None
        if fault is not None:
            target = min(done + fault.view, self.views - 1)
        arm_fault = str(self.rng.choice(["source_arm", "detector_arm"]))
        one_based = None if fault is None else fault.view + 1
        with contextlib.ExitStack() as stack:
            generator = stack.enter_context(
                MockGenerator(
                    time_scale=0.0,
                    warmup_s=0.05,
                    timeout_at_exposure=one_based if kind == "generator_timeout" else None,
                    interlock_open_at_exposure=one_based if kind == "interlock" else None,
                    on_event=recorder("generator"),
                )
            )
            stage = stack.enter_context(
                MockStage.of_scanner(
                    self.scanner, q0[:2], servo_lag_s=0.004, on_event=recorder("stage")
                )
            )
            fakes = {}
            for (arm, joints), host in zip(
                (("source_arm", slice(2, 8)), ("detector_arm", slice(8, 14))), UR_HOSTS, strict=True
            ):
                hooks = {}
                if arm == arm_fault and kind == "controller_silent":
                    hooks["silent_after_servo"] = self.servo_count(target)
                if arm == arm_fault and kind == "protective_stop":
                    hooks["protective_stop_after_servo"] = self.servo_count(target)
                fakes[arm] = stack.enter_context(
                    FakeURController(host, q0[joints], name=arm, **hooks)
                )
            config = folder.parent / f"{folder.name}-session{session}-ur.yaml"
            spec = {
                "source_host": UR_HOSTS[0],
                "detector_host": UR_HOSTS[1],
                "stage_port": stage.port,
                "generator_port": generator.port,
                "detector_maps": str(self.panel_maps()),
            }
            config.write_text(yaml.safe_dump(spec), encoding="utf-8")
            logs = set((study / "scan").glob("generator_commands-*.csv"))
            code = self.run_child(self.command("ur", study, config, session > 1), study, fault, log)
            for arm, fake in fakes.items():
                events += [(t, arm, name) for name, t in fake.events()]
        if fault is not None and kind != "sigkill":
            events.sort()
            exempt = {}
            if kind in ("controller_silent", "protective_stop"):
                fault.injected_s = injection_time(kind, events)
                exempt[arm_fault] = "protective_stop" if kind == "protective_stop" else ""
            elif kind in ("generator_timeout", "interlock"):
                fault.injected_s = injection_time(kind, events)
            time_to_safe(fault, events, exempt)
            command_log = new_command_log(study, logs)
            if kind in STOP_SIGNALS:
                pulses_after_stop(fault, command_log, events)
            write_timeline(log.with_suffix(".timeline.csv"), fault, events, command_log)
            self._check_injected(fault, code, log)
        return code

    def _check_injected(self, fault: FaultRecord, code: int | None, log: Path) -> None:
        if fault.injected_s is None and code == 0:
            fault.note += " not injected (the scan ended first);"
        elif fault.injected_s is not None and fault.time_to_safe_ms is None and fault.note:
            tail = log.read_text(encoding="utf-8", errors="replace")[-600:]
            self.totals.problems.append(f"{fault}: {tail}")


def soak(
    scans: int = 20,
    seed: int = 0,
    views: int = 24,
    kinds: tuple[str, ...] = KINDS,
    work: Path | None = None,
    backends: tuple[str, ...] = BACKENDS,
    gige_interface: str | None = None,
) -> dict:
    """Run the soak; the benchmark's JSON object. ``gige_interface``: the simulated scans'
    panel served over GigE Vision on that address (the camera_gone fault needs it)."""
    unknown = sorted(set(kinds) - set(KINDS))
    if unknown:
        raise ValueError(f"unknown fault kinds {unknown}; kinds are {KINDS}")
    if not backends or set(backends) - set(BACKENDS):
        raise ValueError(f"backends must be some of {BACKENDS}, got {backends}")
    if "controller_silent" in kinds and "ur" not in backends:
        raise ValueError("the controller_silent fault needs the ur backend in backends")
    for kind in SIM_ONLY:
        if kind in kinds and "sim" not in backends:
            raise ValueError(f"the {kind} fault needs the sim backend in backends")
    if "camera_gone" in kinds and gige_interface is None:
        raise ValueError("the camera_gone fault needs --gige-interface (the panel over GigE)")
    if not 8 <= views <= 360:
        raise ValueError(f"views must be in [8, 360], got {views}")
    started = time.perf_counter()
    with contextlib.ExitStack() as stack:
        if work is None:
            work = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="soak-")))
        work.mkdir(parents=True, exist_ok=True)
        state = Soak(work, views, seed, kinds, backends, gige_interface)
        for index in range(scans):
            state.scan(index)
    totals = state.totals
    injected = [f for f in totals.faults if f.injected_s is not None]
    timed = [f for f in injected if f.time_to_safe_ms is not None]
    by_kind: dict[str, float] = {}
    for f in timed:
        by_kind[f.kind] = max(by_kind.get(f.kind, 0.0), f.time_to_safe_ms)
    signalled = [f.time_to_safe_ms for f in timed if state.bound_ms(f) == SIGNALLED_BOUND_MS]
    over = [f for f in timed if f.time_to_safe_ms > state.bound_ms(f)]
    for f in totals.faults:
        if f.xray_after or f.exp_after or f in over:
            totals.problems.append(
                f"{f.kind} in scan {f.scan} session {f.session} ({f.backend} backend) at view "
                f"{f.view}: {f.time_to_safe_ms} ms to SAFE (bound {state.bound_ms(f):.0f}), "
                f"{f.xray_after} pulses after it ({f.exp_after} EXP sent after it);{f.note}"
            )
    xray_by_kind = Counter()
    for f in totals.faults:
        xray_by_kind[f.kind] += f.xray_after
    untimed = [
        f
        for f in injected
        if f.time_to_safe_ms is None and f.kind != "sigkill" and "no timing" not in f.note
    ]
    xray = sum(f.xray_after for f in totals.faults)
    exp_after = sum(f.exp_after for f in totals.faults)
    stops = [f for f in injected if f.kind in STOP_SIGNALS]
    result = {
        "benchmark": "soak",
        "scans": scans,
        "scans_complete": totals.complete,
        "views_per_scan": views,
        "seed": seed,
        "panel_over_gige": gige_interface,
        "faults": len(injected),
        "faults_by_kind": dict(sorted(Counter(f.kind for f in injected).items())),
        "faults_not_injected": len(totals.faults) - len(injected),
        "views_lost": totals.views_lost,
        "corrupt_files": totals.corrupt_files,
        "stray_temp_files": totals.stray_temp_files,
        "x_ray_on_after_fault": xray,
        "x_ray_on_after_fault_by_kind": {k: v for k, v in sorted(xray_by_kind.items()) if v},
        "exp_after_stop": exp_after,
        "pulses_in_flight_at_stop": sum(f.in_flight for f in stops),
        "pulses_in_flight_at_camera_gone": sum(
            f.in_flight for f in injected if f.kind == "camera_gone"
        ),
        "stop_signals_by_backend": dict(sorted(Counter(f.backend for f in stops).items())),
        "max_kill_call_ms": round(
            max((f.certain_s - f.injected_s for f in stops), default=0) * 1e3, 2
        ),
        "resumes": totals.resumes,
        "hangs": totals.hangs,
        "max_time_to_safe_ms": round(max(signalled), 1) if signalled else None,
        "max_time_to_safe_ms_by_kind": {k: round(v, 1) for k, v in sorted(by_kind.items())},
        "time_to_safe_bound_ms": {
            "signalled": SIGNALLED_BOUND_MS,
            **{k: round(v, 1) for k, v in BOUNDS_MS.items()},
            "disk_full_ur_backend": round(state.view_gap_ms + SIGNALLED_BOUND_MS, 1),
            **({"dropped_frame_over_gige": BOUNDS_MS["camera_gone"]} if gige_interface else {}),
        },
        "silent_controller_bound_ms": round(BOUNDS_MS["controller_silent"], 1),
        "silence_s": SILENCE_S,
        "sigkill_mid_write": sum(1 for f in injected if f.note == "mid-write"),
        "disk_full_method": state.disk_full_method,
        "faults_over_bound": len(over),
        "faults_safe_unconfirmed": len(untimed),
        "problems": totals.problems[:20],
        "backends": list(backends),
        "cpu_model": cpu_model(),
        "wall_s": round(time.perf_counter() - started, 1),
    }
    result["targets_met"] = (
        totals.views_lost == 0
        and totals.corrupt_files == 0
        and xray == 0
        and exp_after == 0
        and totals.complete == scans
        and totals.hangs == 0
        and not over
        and not untimed
    )
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scans", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--views", type=int, default=24, help="views per scan")
    parser.add_argument("--kinds", default=",".join(KINDS), help="fault kinds to draw from")
    parser.add_argument("--work", type=Path, default=None, help="keep the studies here")
    parser.add_argument(
        "--backends", default=",".join(BACKENDS), help="backends the scans are drawn from"
    )
    parser.add_argument(
        "--gige-interface",
        default=None,
        help="serve the simulated scans' panel over GigE Vision on this address (127.0.0.5; "
        "the camera_gone fault needs it)",
    )
    args = parser.parse_args()
    if args.work is not None and args.work.exists() and any(args.work.iterdir()):
        parser.error(f"--work {args.work} exists and is not empty")
    kinds = tuple(k for k in args.kinds.split(",") if k)
    backends = tuple(b for b in args.backends.split(",") if b)
    if args.gige_interface is None and "camera_gone" in kinds:
        kinds = tuple(k for k in kinds if k != "camera_gone")  # no camera to lose
    result = soak(
        args.scans, args.seed, args.views, kinds, args.work, backends, args.gige_interface
    )
    print(json.dumps(result))


if __name__ == "__main__":
    main()

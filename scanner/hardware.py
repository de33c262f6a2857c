"""The hardware the scan state machine drives, as typed protocols.

A backend is a set of devices that satisfy these protocols: the UR one (``scanner.ur``: ur-rtde
arms, the serial generator and stage drivers, the GigE Vision panel of ``scanner.gige``) and the
simulated one (``study.simulator``: mock arms on a virtual clock, the mock generator over a pty, a
rendering detector), each found by name in :mod:`scanner.registry`.

Units: joint positions in the plan's joint units (degrees for revolute joints, millimetres for
the lift), times in seconds on the backend's clock, technique in kVp / mA / ms. Every call that
talks to a device takes a timeout and raises :class:`DeviceError` (or a subclass) when the device
does not answer in time or answers wrongly: it never returns a stale or guessed value.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np


class DeviceError(RuntimeError):
    """A device failed, refused, or did not answer in time; the message names device and call."""


class DeviceTimeout(DeviceError):
    """A device did not answer within the call's timeout."""


class ProtectiveStop(DeviceError):
    """An arm or the stage reported a protective stop."""


@dataclass(frozen=True)
class JointState:
    """One reading of a joint group.

    Attributes:
        q: joint positions in joint units (deg, or mm for the lift).
        t_s: the backend clock's time of the reading, s.
        protective_stop: the group's controller is in protective stop.
    """

    q: np.ndarray
    t_s: float
    protective_stop: bool = False


@runtime_checkable
class Clock(Protocol):
    """The backend's time base: wall time for hardware, virtual time for the simulator."""

    def now(self) -> float:
        """Seconds since an arbitrary origin."""
        ...

    def sleep_until(self, t_s: float) -> None:
        """Return at ``t_s`` (immediately when it has passed)."""
        ...


@runtime_checkable
class Arm(Protocol):
    """A joint group driven by one controller: a UR arm (6 joints, deg) or the stage (rotary deg,
    lift mm)."""

    name: str
    joints: tuple[str, ...]

    def connect(self, timeout_s: float) -> None:
        """Open the connection; raises DeviceTimeout when the controller does not answer."""
        ...

    def state(self, timeout_s: float) -> JointState:
        """The measured joint positions now; raises when no fresh reading arrives in time."""
        ...

    def move_to(self, q: np.ndarray, timeout_s: float) -> None:
        """Jerk-limited point-to-point move to ``q``; blocks until it is there (or raises)."""
        ...

    def servo(self, q: np.ndarray, dt_s: float) -> None:
        """Stream one set-point of a timed trajectory, to be reached ``dt_s`` from now."""
        ...

    def stop(self) -> None:
        """Decelerate to standstill now (and leave streaming mode)."""
        ...

    def close(self) -> None:
        """Stop and release the controller; safe to call twice."""
        ...


@dataclass(frozen=True)
class Technique:
    """X-ray technique of one pulse."""

    kv: float
    ma: float
    ms: float

    @property
    def mas(self) -> float:
        return self.ma * self.ms * 1e-3


@dataclass(frozen=True)
class GeneratorStatus:
    """What the generator reports.

    Attributes:
        ready: prepared (warmed up) and able to expose.
        technique: the technique set, or None before one is set.
        interlocks: name -> closed, for each interlock input (e-stop, door, deadman).
        exposures: pulses fired since power-up.
        fault: the latched fault, or None.
    """

    ready: bool
    technique: Technique | None
    interlocks: dict[str, bool] = field(default_factory=dict)
    exposures: int = 0
    fault: str | None = None

    @property
    def interlocks_closed(self) -> bool:
        return bool(self.interlocks) and all(self.interlocks.values())


@dataclass(frozen=True)
class Exposure:
    """One delivered pulse, as the generator reports it."""

    technique: Technique
    sequence: int


@runtime_checkable
class XrayGenerator(Protocol):
    """An X-ray generator: technique, prepare (warm-up), expose one pulse, abort."""

    def connect(self, timeout_s: float) -> None: ...

    def set_technique(self, technique: Technique, timeout_s: float) -> None:
        """Set kV / mA / ms; raises naming the value and the limit when out of range."""
        ...

    def prepare(self, timeout_s: float) -> None:
        """Warm up; returns when ready."""
        ...

    def expose(self, timeout_s: float, permit: Callable[[], None] | None = None) -> Exposure:
        """Fire one pulse at the set technique; refuses (raises) with an interlock open.
        ``permit`` is called immediately before the pulse is commanded; what it raises is
        raised and nothing is commanded."""
        ...

    def abort(self, timeout_s: float) -> None:
        """X-ray off now; returns when the generator confirms."""
        ...

    def status(self, timeout_s: float) -> GeneratorStatus: ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class Frame:
    """One detector read-out: raw counts [row, col] (ADU, uint16 from a real panel) and the
    clock time it was read."""

    counts: np.ndarray
    t_s: float


@runtime_checkable
class Detector(Protocol):
    """A flat panel: open an integration window, read its frame.

    ``serial`` and ``mode`` name the panel and its read-out mode (size, pixel format): the
    offset, gain and defect maps a scan corrects with are bound to both
    (:mod:`scanner.corrections`)."""

    rows: int
    cols: int
    pixel_pitch_mm: float
    serial: str
    mode: str

    def connect(self, timeout_s: float) -> None: ...

    def arm(self, timeout_s: float) -> None:
        """Open the integration window of the next frame (a pulse inside it is integrated)."""
        ...

    def read_frame(self, timeout_s: float) -> Frame:
        """The window's frame (dark when no pulse came); raises DeviceTimeout when none
        arrives, DeviceError when a frame is lost, late or incomplete."""
        ...

    def close(self) -> None: ...


@dataclass
class Backend:
    """The devices of one scanner, and the clock they run on."""

    name: str
    clock: Clock
    stage: Arm
    source_arm: Arm
    detector_arm: Arm
    generator: XrayGenerator
    detector: Detector

    @property
    def groups(self) -> tuple[Arm, Arm, Arm]:
        """Joint groups in the plan's joint order: stage (rotary, lift), source, detector."""
        return (self.stage, self.source_arm, self.detector_arm)

    def close(self) -> None:
        for device in (self.generator, self.detector, *self.groups):
            device.close()


def close_quietly(backend: Backend) -> None:
    """Close the devices; a failure to close must not mask what happened before."""
    try:
        backend.close()
    except Exception:
        pass

"""Moving the scanner between rest poses: to the plan's start before a scan, to park after one
(or after a fault, once SAFE is reached).

A move runs like a scan without X-rays. Before anything moves: the joint groups and the
generator connect, the interlocks (e-stop, door, deadman) must be closed, the joints are read
(a protective stop refuses), the move is planned from the measured joints and checked
(:func:`trajectories.move.plan_move`: limits, clearance along the whole motion, the route),
shown and confirmed (a scanner already within the scan's start tolerance of the goal is left
there, nothing asked). The generator is never prepared, so no pulse can fire. The move's samples
are then streamed to the three joint groups in time, as the scan streams its approach, with
the interlocks read every :data:`INTERLOCK_POLL_S` of motion; the groups must settle within
the scan's start tolerance of the goal, and leave streaming mode. Any failure while moving
goes the scan's SAFE way: X-ray off first, then every group stops, and :class:`MoveFault`
says why and where the arms stopped. The operator's stop (:mod:`scanner.stop`) is checked
before every set-point, and its watchdog stops the arms itself when the move has not reached
SAFE within a few milliseconds of it. The caller owns the devices (connects nothing it did not
open, closes nothing).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from scanner.hardware import Backend, DeviceError
from scanner.scan import (
    GROUP_SLICES,
    SETTLE_POLL_S,
    OperatorDeclined,
    PreflightError,
    ScanSettings,
    measured_joints,
    stop_safely,
)
from scanner.stop import StopRequest
from trajectories.errors import PlanningError
from trajectories.model import ScannerModel
from trajectories.move import JointMove, plan_move

INTERLOCK_POLL_S = 0.1
"""Motion time between interlock readings while moving, s."""


class MoveFault(RuntimeError):
    """A move stopped after it started: X-ray off, every joint group stopped."""


@dataclass(frozen=True)
class MoveResult:
    """A finished move.

    Attributes:
        target: what it went to, in words.
        move: the planned move that ran; None when the scanner already stood within the
            start tolerance of the goal (nothing moved, nothing was asked).
        reached_q: the measured joints once settled (14,), plan units.
        error: largest |reached - goal| over the joints, deg (mm for the lift).
    """

    target: str
    move: JointMove | None
    reached_q: np.ndarray
    error: float


def move_scanner(
    backend: Backend,
    model: ScannerModel,
    goal_q: np.ndarray,
    target: str,
    *,
    settings: ScanSettings | None = None,
    confirm: Callable[[str], bool] = lambda _q: True,
    say: Callable[[str], None] = lambda _m: None,
    stop: StopRequest | None = None,
) -> MoveResult:
    """Move the scanner from its measured joints to ``goal_q`` (plan units, (14,)).

    Raises PreflightError (naming the check), OperatorDeclined or OperatorStop before anything
    moves, MoveFault after SAFE when the move fails on the way (``stop``, the operator's stop
    request, included) or does not end within ``settings.start_tolerance`` of the goal.
    """
    settings = settings or ScanSettings()
    stop = stop or StopRequest()
    timeout = settings.device_timeout_s
    stop.check(f"the move to {target}")
    try:
        for device in (*backend.groups, backend.generator):
            device.connect(timeout)
        _check_interlocks(backend, timeout)
        start = measured_joints(backend, timeout)
        move = plan_move(model, start, goal_q, target)
    except PlanningError as err:
        raise PreflightError(f"{err}: nothing moved") from err
    except Exception as err:  # a device's refusal or failure, before anything moved
        raise PreflightError(f"move to {target} refused: {err}: nothing moved") from err
    offset = float(np.abs(move.goal_q - move.start_q).max())
    if offset <= settings.start_tolerance:
        say(
            f"already at {target}: largest joint offset {offset:.3f} (tolerance "
            f"{settings.start_tolerance}); nothing to move"
        )
        return MoveResult(target, None, start, offset)
    say(f"move to {target}: {move.headline()}\n{move.table()}")
    with stop.interrupting():
        if not confirm(f"Move the scanner to {target}? {move.headline()}"):
            raise OperatorDeclined(f"operator declined the move to {target}: nothing moved")
    with stop.guarding(lambda: stop_safely(backend, timeout)) as guard, stop.deferring():
        try:
            _stream(backend, move, timeout, stop)
            reached = _settled(backend, move, settings, stop)
            for group in backend.groups:  # leave streaming mode, at rest on the goal
                group.stop()
        except BaseException as err:  # the operator's stop included: X-ray off, arms stop
            guard.acknowledge()
            problems = stop_safely(backend, timeout)
            try:
                where = f"; arms at {np.round(measured_joints(backend, timeout), 2).tolist()}"
            except Exception:
                where = ""
            reason = stop.explain(err)
            outcome = "; ".join(problems) if problems else "X-ray off, arms stopped"
            raise MoveFault(f"move to {target} stopped: {reason} ({outcome}{where})") from err
    error = float(np.abs(reached - move.goal_q).max())
    say(f"at {target}: largest joint error {error:.3f} (tolerance {settings.start_tolerance})")
    return MoveResult(target, move, reached, error)


def _check_interlocks(backend: Backend, timeout_s: float) -> None:
    status = backend.generator.status(timeout_s)
    if not status.interlocks_closed:
        opened = [name for name, closed in status.interlocks.items() if not closed]
        raise DeviceError(f"interlocks open: {opened or 'none reported'}")


def _stream(backend: Backend, move: JointMove, timeout_s: float, stop: StopRequest) -> None:
    """Stream the move's samples to the groups in time (each once the operator's stop is
    checked); read the interlocks on the way."""
    clock = backend.clock
    origin = clock.now()
    checked = 0.0
    for k in range(1, len(move.t_s)):
        dt = float(move.t_s[k] - move.t_s[k - 1])
        if dt <= 0:
            continue
        with stop.commanding(f"move set-point at {move.t_s[k]:.3f} s"):
            for group, idx in zip(backend.groups, GROUP_SLICES, strict=True):
                group.servo(move.q[k, idx], dt)
        clock.sleep_until(origin + move.t_s[k])
        if move.t_s[k] - checked >= INTERLOCK_POLL_S:
            _check_interlocks(backend, timeout_s)
            checked = float(move.t_s[k])


def _settled(
    backend: Backend, move: JointMove, settings: ScanSettings, stop: StopRequest
) -> np.ndarray:
    """The measured joints once every one is within the start tolerance of the move's goal;
    groups that lag get ``settle_s`` after the last set-point."""
    goal, clock = move.goal_q, backend.clock
    deadline = clock.now() + settings.settle_s
    while True:
        stop.check("the move's settling")
        q = measured_joints(backend, settings.device_timeout_s)
        error = np.abs(q - goal)
        worst = int(np.argmax(error))
        if error[worst] <= settings.start_tolerance:
            return q
        if clock.now() >= deadline:
            raise DeviceError(
                f"joint {move.joint_names[worst]} is at {q[worst]:.3f}, the goal "
                f"{goal[worst]:.3f} (tolerance "
                f"{settings.start_tolerance}) {settings.settle_s} s after the last set-point"
            )
        clock.sleep_until(clock.now() + SETTLE_POLL_S)

"""The operator's stop: a stop signal becomes a request that no code on the scan's path can miss.

While a session owns the scanner (:func:`stop_signals`), SIGINT (Ctrl-C), SIGTERM (a service
manager's stop), SIGHUP (the terminal closed) and SIGQUIT (Ctrl-\\) set one
:class:`StopRequest`. Two paths act on it, neither waiting for the other:

- the exposure loop, in the main thread: every command that moves the scanner or exposes is
  sent through :meth:`StopRequest.commanding` or checked by :meth:`StopRequest.check` right
  before it is written (the generator's ``EXP`` by its link, under the link's lock), so nothing
  is commanded once the request is set; the loop then goes to SAFE;
- a watchdog thread, woken by the signal itself (``signal.set_wakeup_fd``: the byte is written
  by the C-level handler, wherever the main thread is), which runs the guards' actions
  (X-ray off, every joint group stopped) when the loop has not reached SAFE within
  :data:`GRACE_S` of the request.

Python runs a signal's handler in the main thread between bytecodes only: a handler that raised
(KeyboardInterrupt) surfaced wherever that thread was, e.g. inside a ``try`` that caught it or a
call that retried. Here the handler only sets the request, so nothing can swallow it; where the
main thread waits for the operator (a confirmation) or owns no moving device
(:meth:`StopRequest.deferring` not active) it also raises :class:`OperatorStop`, Ctrl-C's usual
behaviour.
"""

from __future__ import annotations

import contextlib
import logging
import select
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable, Iterator

log = logging.getLogger(__name__)

STOP_SIGNALS: dict[signal.Signals, str] = {
    signal.SIGINT: "SIGINT (Ctrl-C)",
    signal.SIGTERM: "SIGTERM (a stop from the system or a service manager)",
    signal.SIGHUP: "SIGHUP (the terminal closed)",
    signal.SIGQUIT: "SIGQUIT (Ctrl-\\)",
}
"""The signals that stop the scanner, and how a reason names each."""
GRACE_S = 0.005
"""How long the watchdog leaves a stop to the exposure loop before acting itself, s."""
COMMAND_WAIT_S = 0.02
"""Longest the watchdog waits for a command already under way before it stops the devices, s
(a command that does not return in time is followed by the stop anyway)."""
SWITCH_INTERVAL_S = 0.001
"""The interpreter's thread switch interval while a session owns the scanner, s (Python's
default is 5 ms): a thread that waits for the GIL (the watchdog, the threads that stop the joint
groups, the mock devices' threads) gets it within about this long of a busy main thread."""
_CODE_SET = b"\0"
"""The watchdog's wake-up byte for a request set by code (a signal writes its number)."""


class OperatorStop(KeyboardInterrupt):
    """The scanner was told to stop (a stop signal, or :meth:`StopRequest.set`).

    A KeyboardInterrupt, so that whatever handles Ctrl-C handles every stop signal alike."""


class StopRequest:
    """A request to stop the scanner now, set once and never cleared.

    Attributes:
        reason: why, in words (None until set).
        signum: the signal that set it (None: set by code).
        t_s: ``time.monotonic()`` when it was set, s.
    """

    def __init__(self) -> None:
        self.reason: str | None = None
        self.signum: int | None = None
        self.t_s: float | None = None
        # set by a signal handler too, which runs in the main thread between any two bytecodes:
        # it takes no lock (a plain flag, the reason written before it)
        self._requested = False
        self._lock = threading.RLock()  # guards the guards and the watchdog's socket
        self._commands = threading.Lock()  # held while a command is checked and sent
        self._guards: list[_Guard] = []
        self._deferring = 0
        self._wake: socket.socket | None = None  # the watchdog's wake-up, while it runs

    def __repr__(self) -> str:
        return f"StopRequest(reason={self.reason!r})" if self.is_set else "StopRequest()"

    @property
    def is_set(self) -> bool:
        return self._requested

    def set(self, reason: str, signum: int | None = None) -> None:
        """Request the stop (the first reason is kept); wakes the watchdog."""
        if self._requested:
            return
        self.reason, self.signum, self.t_s = reason, signum, time.monotonic()
        self._requested = True
        self._wake_watchdog()

    def _wake_watchdog(self) -> None:
        wake = self._wake
        if wake is not None:
            with contextlib.suppress(OSError):  # a full buffer: the watchdog is awake already
                wake.send(_CODE_SET)

    def check(self, what: str) -> None:
        """Raise :class:`OperatorStop` naming ``what`` (the command not sent) once requested."""
        if self._requested:
            raise OperatorStop(f"stopped by {self.reason}: {what} not sent")

    def explain(self, err: BaseException) -> str:
        """Why a scan or move went to SAFE on ``err``, in words: the stop (and what it cut
        short, e.g. a pulse the watchdog's ABORT ended) once requested, else the error."""
        if self._requested:
            reason = f"stopped by {self.reason}"
            if not isinstance(err, OperatorStop):
                reason += f" ({type(err).__name__}: {err})"
            return reason
        if isinstance(err, KeyboardInterrupt):
            return "interrupted by the operator (Ctrl-C)"
        return f"{type(err).__name__}: {err}"

    @contextlib.contextmanager
    def commanding(self, what: str) -> Iterator[None]:
        """Check, then send a command that moves the scanner inside this block: the watchdog
        stops the devices only once such a command has returned (or after
        :data:`COMMAND_WAIT_S`), so no command follows its stop."""
        with self._commands:
            self.check(what)
            yield

    @contextlib.contextmanager
    def deferring(self) -> Iterator[None]:
        """While inside (devices moving or exposing), a stop signal only sets the request: the
        loop acts on it at its next check, the watchdog at once."""
        self._deferring += 1
        try:
            yield
        finally:
            self._deferring -= 1

    @contextlib.contextmanager
    def interrupting(self) -> Iterator[None]:
        """While inside (e.g. waiting for the operator's answer), a stop signal also raises
        :class:`OperatorStop`, even within :meth:`deferring`."""
        saved, self._deferring = self._deferring, 0
        try:
            if self._requested:
                raise OperatorStop(f"stopped by {self.reason}")
            yield
        finally:
            self._deferring = saved

    @contextlib.contextmanager
    def guarding(self, action: Callable[[], None], grace_s: float = GRACE_S) -> Iterator[_Guard]:
        """While inside, a stop request not acknowledged within ``grace_s`` runs ``action``
        (e.g. X-ray off and every joint group stopped) on the watchdog thread, after any
        command under way. The loop calls the guard's ``acknowledge()`` once it has taken the
        stop in hand (SAFE), which leaves it to the loop."""
        guard = _Guard(action, grace_s)
        with self._lock:
            self._guards.append(guard)
        if self.is_set:  # set before: the watchdog was woken before this guard existed
            self._wake_watchdog()
        try:
            yield guard
        finally:
            with self._lock:
                self._guards.remove(guard)

    # -- the watchdog --------------------------------------------------------------------------

    def _handle_signal(self, signum: int, _frame: object) -> None:
        self.set(STOP_SIGNALS[signal.Signals(signum)], signum)
        if not self._deferring:
            raise OperatorStop(f"stopped by {self.reason}")

    def _watch(self, wake: socket.socket) -> None:
        """The watchdog: wakes on every signal byte and code-set request; acts on guards."""
        while True:
            select.select([wake], [], [])
            try:
                data = wake.recv(64)
            except OSError:  # closed: the session is over
                return
            if not data:
                return
            for byte in data:  # a signal's number, or 0 for a request set by code
                with contextlib.suppress(ValueError):
                    sig = signal.Signals(byte)
                    if sig in STOP_SIGNALS:
                        self.set(STOP_SIGNALS[sig], int(sig))
            if self.is_set:
                self._act()

    def _act(self) -> None:
        """Run the action of every guard the loop has not acknowledged within its grace."""
        with self._lock:
            guards = list(self._guards)
        for guard in guards:
            if guard.acknowledged.wait(guard.grace_s):
                continue
            took = self._commands.acquire(timeout=COMMAND_WAIT_S)  # a command under way first
            if took:
                self._commands.release()
            guard.run()


class _Guard:
    """An action the watchdog runs, once, on a stop the loop has not acknowledged."""

    def __init__(self, action: Callable[[], None], grace_s: float) -> None:
        self.action, self.grace_s = action, grace_s
        self.acknowledged = threading.Event()
        self.ran = False

    def acknowledge(self) -> None:
        """The loop has the stop in hand: the watchdog leaves it alone."""
        self.acknowledged.set()

    def run(self) -> None:
        """Run the action (on the watchdog thread only) unless it ran already."""
        if self.ran:
            return
        self.ran = True
        try:
            self.action()
        except Exception:  # the loop's SAFE stops the devices again and reports what fails
            log.exception("the stop watchdog's action failed")


@contextlib.contextmanager
def stop_signals(stop: StopRequest) -> Iterator[StopRequest]:
    """Route the stop signals to ``stop`` and run its watchdog while inside.

    Signal handlers can only be installed by the main thread; elsewhere only the watchdog runs
    (for requests set by code). The previous handlers and wake-up descriptor are restored on
    exit."""
    wake, signal_end = socket.socketpair()
    signal_end.setblocking(False)
    main = threading.current_thread() is threading.main_thread()
    previous: dict[signal.Signals, object] = {}
    previous_fd = -1
    with stop._lock:
        if stop._wake is not None:
            raise RuntimeError("a StopRequest is watched by one stop_signals at a time")
        stop._wake = signal_end
    watchdog = threading.Thread(target=stop._watch, args=(wake,), name="stop-watchdog")
    watchdog.daemon = True
    switch_interval = sys.getswitchinterval()
    sys.setswitchinterval(min(switch_interval, SWITCH_INTERVAL_S))
    try:
        if main:
            for sig in STOP_SIGNALS:
                previous[sig] = signal.signal(sig, stop._handle_signal)
            previous_fd = signal.set_wakeup_fd(signal_end.fileno(), warn_on_full_buffer=False)
        watchdog.start()
        if stop.is_set:  # set before the watchdog ran
            stop._wake_watchdog()
        yield stop
    finally:
        sys.setswitchinterval(switch_interval)
        if main:
            signal.set_wakeup_fd(previous_fd)
            for sig, handler in previous.items():
                signal.signal(sig, handler)
        with stop._lock:
            stop._wake = None
        signal_end.close()  # the watchdog reads the end of input and returns
        if watchdog.is_alive() and watchdog is not threading.current_thread():
            watchdog.join(timeout=1.0)
        wake.close()

"""ur-rtde's interfaces of one arm in a worker process, every call under a deadline.

ur-rtde's constructors hold the GIL and wait for the controller without a timeout (a controller
that answers the RTDE handshake but not the recipe set-up froze the whole scanner, X-ray
generator included), and its blocking calls (stopJ, servoStop, a moveJ's acknowledgement) wait
on the controller's control script for up to minutes. So the interfaces live in a child process
(:mod:`scanner.ur_worker`) and this process waits for every answer with a deadline, on a pipe,
the GIL free. When a deadline passes the worker is killed: its sockets close as if the cable
were pulled, and the call raises :class:`~scanner.hardware.DeviceTimeout`; the client is then
closed and every later call raises :class:`~scanner.hardware.DeviceError`.

A round trip costs tens of microseconds, so calls that belong together go in one request
(:meth:`URClient.calls`). Calls from several threads (the watchdog's stop while the exposure
loop streams) take turns: one request and its answer at a time.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import threading
import time
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from scanner.hardware import DeviceError, DeviceTimeout

WORKER = Path(__file__).with_name("ur_worker.py")

Call = tuple[str, str, tuple]
"""``(interface, method, args)``: interface ``"receive"`` or ``"control"``."""


class URClient:
    """One arm's ur-rtde client in a worker process.

    Args:
        label: who is talking to whom, the start of every message (``"source_arm: ..."``).
        host: the controller's address.
    """

    def __init__(self, label: str, host: str) -> None:
        self.label, self.host = label, host
        self._process: subprocess.Popen[bytes] | None = None
        self._requests: Connection | None = None
        self._answers: Connection | None = None
        self._owed = 0  # answers not yet read: the worker answers every request, in order
        self._turn = threading.RLock()  # one request and its answer at a time

    @property
    def alive(self) -> bool:
        return self._process is not None

    def open(
        self,
        frequency_hz: float,
        variables: list[str],
        upper_range_registers: bool,
        timeout_s: float,
    ) -> None:
        """Start the worker and construct the receive interface (``variables`` at
        ``frequency_hz``, -1 for the controller's rate), then the control interface (uploading
        its script; on registers 24-47 with ``upper_range_registers``), within ``timeout_s``;
        raises DeviceTimeout (worker killed) or DeviceError (ur-rtde refused)."""
        if self.alive:
            raise DeviceError(f"{self.label}: connect: already connected to {self.host}")
        self._process = subprocess.Popen(
            [sys.executable, str(WORKER)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            close_fds=True,
        )
        stdin, stdout = self._process.stdin, self._process.stdout
        assert stdin is not None and stdout is not None
        self._requests = Connection(os.dup(stdin.fileno()), readable=False)
        self._answers = Connection(os.dup(stdout.fileno()), writable=False)
        stdin.close()
        stdout.close()
        request = ("open", self.host, frequency_hz, variables, upper_range_registers)
        what = "connect: ur-rtde's set-up (RTDE recipes, control script upload)"
        answer = self._ask(request, timeout_s, what)
        if answer[0] == "error":
            self._end()
            _, where, message = answer
            port = "RTDE receive on 30004" if where == "receive" else "its control script"
            raise DeviceError(
                f"{self.label}: connect: ur-rtde could not open {port} on {self.host}: {message}"
            )

    def calls(self, calls: list[Call], timeout_s: float, what: str) -> list[Any]:
        """The results of ``calls`` made in order in the worker; raises DeviceTimeout when they
        do not return within ``timeout_s`` (the worker is then killed), DeviceError when one
        raises (naming it) or the client is closed."""
        if not self.alive:
            raise DeviceError(f"{self.label}: {what}: not connected to {self.host}")
        answer = self._ask(("calls", calls), timeout_s, what)
        if answer[0] == "error":
            _, where, message = answer
            raise DeviceError(
                f"{self.label}: {what}: ur-rtde {where} failed on {self.host}: {message}"
            )
        return answer[1]

    def call(self, interface: str, method: str, *args: Any, timeout_s: float, what: str) -> Any:
        """One call (:meth:`calls`)."""
        return self.calls([(interface, method, args)], timeout_s, what)[0]

    def close(self, timeout_s: float) -> None:
        """Drop the interfaces (ur-rtde disconnects) and end the worker, killed when it does
        not finish within ``timeout_s``; safe to call twice."""
        with self._turn:
            if not self.alive:
                return
            with contextlib.suppress(DeviceError):
                self._ask(("close",), timeout_s, "close")
            self._end(timeout_s)

    def _ask(self, request: tuple, timeout_s: float, what: str) -> tuple:
        with self._turn:
            if self._requests is None or self._answers is None:  # ended by another thread
                raise DeviceError(f"{self.label}: {what}: not connected to {self.host}")
            return self._ask_now(request, timeout_s, what)

    def _ask_now(self, request: tuple, timeout_s: float, what: str) -> tuple:
        assert self._requests is not None and self._answers is not None
        t0 = time.monotonic()
        try:
            self._requests.send(request)
            self._owed += 1
            # an earlier call interrupted while it waited (Ctrl-C) left its answer unread: it
            # comes first, and is dropped, within this call's deadline
            while self._answers.poll(max(t0 + timeout_s - time.monotonic(), 0.0)):
                answer = self._answers.recv()
                self._owed -= 1
                if not self._owed:
                    return answer
        except (OSError, EOFError) as exc:
            code = self._end()
            raise DeviceError(
                f"{self.label}: {what}: the ur-rtde client of {self.host} ended (exit code "
                f"{code}): {exc}"
            ) from exc
        waited = time.monotonic() - t0
        self._end()
        raise DeviceTimeout(
            f"{self.label}: {what}: {self.host} did not answer within {timeout_s:g} s (waited "
            f"{waited:.3f} s); its ur-rtde client was ended and the connection dropped"
        )

    def _end(self, timeout_s: float = 0.0) -> int | None:
        """End the worker (killed unless it exits within ``timeout_s``); its exit code."""
        process, self._process = self._process, None
        if process is None:
            return None
        try:
            process.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
        for channel in (self._requests, self._answers):
            if channel is not None:
                channel.close()
        self._requests = self._answers = None
        self._owed = 0
        return process.returncode

"""Run the fake controller as a subprocess for tests and tools."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

from sim.ur_controller.server import READY_LINE

# -- launcher for tests and tools ----------------------------------------------------------------


class FakeURController:
    """Run ``python -m sim.ur_controller`` as a subprocess for the life of a ``with`` block.

    Waits until the process reports that all its ports are open (raises RuntimeError with the
    process's log when it exits first, e.g. because another process holds a port on ``host``,
    or when ``startup_timeout_s`` passes), and terminates it (SIGTERM, then SIGKILL) on exit.
    One fake per host address.
    """

    def __init__(
        self,
        host: str,
        home_deg: Sequence[float],
        *,
        protective_stop_after_servo: int | None = None,
        silent_after_servo: int | None = None,
        silent_after_handshake: bool = False,
        name: str | None = None,
        servo_lag_s: float | None = None,
        verbose: bool = False,
        startup_timeout_s: float = 15.0,
    ) -> None:
        if len(home_deg) != 6:
            raise ValueError(f"home_deg needs 6 joint positions, got {len(home_deg)}")
        self.host = host
        self.home_deg = tuple(float(v) for v in home_deg)
        self.name = name or f"ur@{host}"
        self.startup_timeout_s = startup_timeout_s
        self.args = [
            sys.executable,
            "-m",
            "sim.ur_controller",
            "--host",
            host,
            "--home-deg",
            *(repr(v) for v in self.home_deg),
            "--name",
            self.name,
        ]
        if protective_stop_after_servo is not None:
            self.args += ["--protective-stop-after-servo", str(protective_stop_after_servo)]
        if silent_after_servo is not None:
            self.args += ["--silent-after-servo", str(silent_after_servo)]
        if silent_after_handshake:
            self.args.append("--silent-after-handshake")
        if servo_lag_s is not None:
            self.args += ["--servo-lag-s", repr(servo_lag_s)]
        if verbose:
            self.args.append("--verbose")
        self.process: subprocess.Popen[bytes] | None = None
        self._log = tempfile.TemporaryFile()

    def start(self) -> FakeURController:
        root = Path(__file__).resolve().parents[2]  # the repository: this checkout's sim
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (str(root), env.get("PYTHONPATH", "")) if p)
        self.process = subprocess.Popen(
            self.args, stdin=subprocess.DEVNULL, stdout=self._log, stderr=self._log, env=env
        )
        deadline = time.monotonic() + self.startup_timeout_s
        ready = f"{READY_LINE} {self.host}\n"
        while ready not in self.log_text():
            if self.process.poll() is not None:
                raise RuntimeError(
                    f"fake UR controller {self.name} exited with {self.process.returncode}:\n"
                    + self.log_text()
                )
            if time.monotonic() > deadline:
                self.stop()
                raise RuntimeError(
                    f"fake UR controller {self.name} did not open its ports on {self.host} "
                    f"within {self.startup_timeout_s} s:\n" + self.log_text()
                )
            time.sleep(0.02)
        return self

    def log_text(self) -> str:
        """What the process wrote to stdout and stderr so far.

        Read with ``pread``: the child writes through a descriptor that shares this file's
        offset, so seeking here would make its next line overwrite the start of the log.
        """
        fd = self._log.fileno()
        return os.pread(fd, os.fstat(fd).st_size, 0).decode(errors="replace")

    def events(self) -> list[tuple[str, float]]:
        """The ``EVENT`` lines printed so far (:mod:`sim.ur_controller.events`): name and
        ``time.monotonic()`` of each, oldest first."""
        out = []
        for line in self.log_text().splitlines():
            words = line.split()
            if len(words) == 3 and words[0] == "EVENT":
                out.append((words[1], float(words[2])))
        return out

    def stop(self) -> None:
        process, self.process = self.process, None
        if process is None or process.poll() is not None:
            return
        process.terminate()
        try:
            process.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=5.0)

    def __enter__(self) -> FakeURController:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def __del__(self) -> None:
        with contextlib.suppress(Exception):
            self.stop()
            self._log.close()

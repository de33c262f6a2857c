"""The fake controller's process: every port served on one host address; ``main`` is the
entry point of ``python -m sim.ur_controller``.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import signal
import sys
from collections.abc import Sequence

from sim.ur_controller.arm import CONTROL_PERIOD_S
from sim.ur_controller.controller import Controller
from sim.ur_controller.dashboard import DashboardSession
from sim.ur_controller.rtde import RTDESession
from sim.ur_controller.script_ports import ScriptSession

log = logging.getLogger("sim.ur_controller")


# -- ports, versions --------------------------------------------------------------------------

RTDE_PORT = 30004
DASHBOARD_PORT = 29999
SCRIPT_PORTS = (30001, 30002, 30003)
ALL_PORTS = (RTDE_PORT, DASHBOARD_PORT, *SCRIPT_PORTS)

READY_LINE = "sim.ur_controller ready on"
"""Printed to stdout (followed by the host) once every port is open."""

# -- the server process --------------------------------------------------------------------------


class FakeServer:
    """The fake controller's servers and 500 Hz loop on one host address (asyncio)."""

    def __init__(
        self,
        host: str,
        controller: Controller,
        serial_number: str = "20235500001",
        *,
        rtde_silent_after_handshake: bool = False,
    ) -> None:
        self.host = host
        self.rtde_silent_after_handshake = rtde_silent_after_handshake
        self.controller = controller
        self.serial_number = serial_number
        self.rtde_sessions: set[RTDESession] = set()
        self.input_owners: dict[str, RTDESession] = {}
        self.requests: list[str] = []

    def record(self, request: str) -> None:
        """Log one request from a client (``--verbose`` prints them)."""
        if len(self.requests) < 1000:
            self.requests.append(request)
        log.debug("%s: %s", self.controller.name, request)

    async def serve(self, stop: asyncio.Event) -> None:
        loop = asyncio.get_running_loop()
        servers = [
            await loop.create_server(lambda: RTDESession(self), self.host, RTDE_PORT),
            await loop.create_server(lambda: DashboardSession(self), self.host, DASHBOARD_PORT),
        ]
        for port in SCRIPT_PORTS:
            servers.append(
                await loop.create_server(
                    lambda port=port: ScriptSession(self, port), self.host, port
                )
            )
        log.info("%s: serving on %s ports %s", self.controller.name, self.host, ALL_PORTS)
        print(f"{READY_LINE} {self.host}", flush=True)
        control = asyncio.create_task(self._control_loop())
        await stop.wait()
        control.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await control
        for server in servers:
            server.close()
        for session in list(self.rtde_sessions):
            if session.transport is not None:
                session.transport.close()
        for server in servers:
            await server.wait_closed()

    async def _control_loop(self) -> None:
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        ctl = self.controller
        while True:
            due = t0 + (ctl.ticks + 1) * CONTROL_PERIOD_S
            delay = due - loop.time()
            if delay > 0:
                await asyncio.sleep(delay)
            behind = int((loop.time() - t0) / CONTROL_PERIOD_S) - ctl.ticks
            if behind > 250:  # stalled (e.g. a suspended process): do not replay the gap
                t0 += (behind - 1) * CONTROL_PERIOD_S
                behind = 1
            try:
                for _ in range(max(behind, 1)):
                    ctl.tick()
                for session in list(self.rtde_sessions):
                    session.publish()
            except Exception:
                log.exception("%s: control loop", ctl.name)


def main(argv: Sequence[str] | None = None) -> int:
    """Run one fake controller until it is terminated (``python -m sim.ur_controller``);
    returns the exit status."""
    parser = argparse.ArgumentParser(
        prog="python -m sim.ur_controller", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("--host", default="127.0.0.2", help="address to serve on")
    parser.add_argument(
        "--home-deg", type=float, nargs=6, required=True, metavar="Q", help="start joints, deg"
    )
    parser.add_argument("--protective-stop-after-servo", type=int, default=None, metavar="N")
    parser.add_argument(
        "--silent-after-servo",
        type=int,
        default=None,
        metavar="N",
        help="stop answering anything on the N-th servoJ command",
    )
    parser.add_argument(
        "--silent-after-handshake",
        action="store_true",
        help="RTDE answers the protocol-version request only",
    )
    parser.add_argument("--servo-lag-s", type=float, default=0.004)
    parser.add_argument("--name", default=None, help="label in the log")
    parser.add_argument("--verbose", action="store_true", help="log every client request")
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.WARNING,
        format="%(asctime)s %(levelname)s %(message)s",
        stream=sys.stderr,
    )
    controller = Controller(
        args.home_deg,
        name=args.name or f"ur@{args.host}",
        protective_stop_after_servo=args.protective_stop_after_servo,
        silent_after_servo=args.silent_after_servo,
        servo_lag_s=args.servo_lag_s,
    )
    server = FakeServer(
        args.host, controller, rtde_silent_after_handshake=args.silent_after_handshake
    )

    async def run() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, stop.set)
        await server.serve(stop)

    try:
        asyncio.run(run())
    except OSError as exc:
        log.error("%s: cannot serve on %s: %s", controller.name, args.host, exc)
        return 1
    return 0

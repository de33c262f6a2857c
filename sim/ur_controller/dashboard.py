"""The fake controller's dashboard server (port 29999).

Dashboard server, port 29999: the welcome line and the replies of PolyScope 5 to the
commands ur-rtde's ``DashboardClient`` sends (``PolyscopeVersion``, ``get serial number``,
``is in remote control``, ``robotmode``, ``safetymode``, ``safetystatus``, ``programState``,
``running``, ``power on``/``off``, ``brake release``, ``unlock protective stop``,
``close safety popup``, ``close popup``, ``stop``, ``play``, ``pause``, ``load``, ...).
"""

from __future__ import annotations

import asyncio
from typing import TYPE_CHECKING

from sim.ur_controller.controller import (
    CONTROLLER_VERSION,
    POLYSCOPE_VERSION,
    ROBOT_MODE_IDLE,
    ROBOT_MODE_NAMES,
    ROBOT_MODE_POWER_OFF,
    ROBOT_MODE_RUNNING,
    RUNTIME_NAMES,
    RUNTIME_PLAYING,
    SAFETY_MODE_NAMES,
    SAFETY_MODE_NORMAL,
)

if TYPE_CHECKING:
    from sim.ur_controller.server import FakeServer


# -- dashboard server ----------------------------------------------------------------------------


class DashboardSession(asyncio.Protocol):
    """One dashboard-server connection: a line in, a line out."""

    def __init__(self, server: FakeServer) -> None:
        self.server = server
        self.ctl = server.controller
        self.buffer = b""
        self.transport: asyncio.Transport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        if not self.ctl.silent:
            transport.write(b"Connected: Universal Robots Dashboard Server\n")

    def data_received(self, data: bytes) -> None:
        if self.ctl.silent:
            return
        self.buffer += data
        while b"\n" in self.buffer:
            line, self.buffer = self.buffer.split(b"\n", 1)
            command = line.decode(errors="replace").strip()
            if not command:
                continue
            self.server.record(f"dashboard {command}")
            reply = self.reply(command)
            assert self.transport is not None
            self.transport.write(reply.encode() + b"\n")
            if command.lower() == "quit":
                self.transport.close()
                return

    def reply(self, command: str) -> str:
        ctl = self.ctl
        lower = command.lower()
        word, _, rest = command.partition(" ")
        if lower == "polyscopeversion":
            return POLYSCOPE_VERSION
        if lower == "version":
            return ".".join(str(v) for v in CONTROLLER_VERSION)
        if lower == "get serial number":
            return self.server.serial_number
        if lower == "get robot model":
            return "UR5"
        if lower == "is in remote control":
            return "true"
        if lower == "robotmode":
            return f"Robotmode: {ROBOT_MODE_NAMES.get(ctl.robot_mode, 'UNKNOWN')}"
        if lower in ("safetymode", "safetystatus"):
            label = "Safetymode" if lower == "safetymode" else "Safetystatus"
            return f"{label}: {SAFETY_MODE_NAMES.get(ctl.safety_mode, 'FAULT')}"
        if lower == "programstate":
            return f"{RUNTIME_NAMES.get(ctl.runtime_state, 'STOPPED')} {ctl.program_name}"
        if lower == "running":
            return f"Program running: {str(ctl.runtime_state == RUNTIME_PLAYING).lower()}"
        if lower == "get loaded program":
            return f"Loaded program: {ctl.program_name}"
        if lower == "isprogramsaved":
            return f"true {ctl.program_name}"
        if lower == "get operational mode":
            return "NONE"
        if lower == "power on":
            if ctl.robot_mode == ROBOT_MODE_POWER_OFF:
                ctl.robot_mode = ROBOT_MODE_IDLE
            return "Powering on"
        if lower == "power off":
            ctl.stop_program("power off")
            ctl.robot_mode = ROBOT_MODE_POWER_OFF
            return "Powering off"
        if lower == "brake release":
            if ctl.robot_mode in (ROBOT_MODE_IDLE, 4):
                ctl.robot_mode = ROBOT_MODE_RUNNING
            return "Brake releasing"
        if lower == "unlock protective stop":
            return ctl.unlock_protective_stop()
        if lower == "close safety popup":
            return "closing safety popup"
        if lower == "close popup":
            return "closing popup"
        if word.lower() == "popup":
            return "showing popup"
        if word.lower() == "addtolog":
            return "Added log message"
        if lower == "restart safety":
            ctl.safety_mode = SAFETY_MODE_NORMAL
            ctl.stop_program("restart safety")
            ctl.robot_mode = ROBOT_MODE_POWER_OFF
            return "Restarting safety"
        if lower == "stop":
            ctl.stop_program("dashboard stop")
            return "Stopped"
        if lower == "pause":
            return "Pausing program" if ctl.pause() else "Failed to execute: pause"
        if lower == "play":
            return "Starting program" if ctl.play() else "Failed to execute: play"
        if word.lower() == "load":
            ctl.program_name = rest.strip()
            return f"Loading program: {rest.strip()}"
        if lower == "shutdown":
            return "Shutting down"
        if lower == "quit":
            return "Disconnected"
        return f"could not understand: '{command}'"

"""The fake controller's RTDE server (port 30004) and the RTDE types of its variables.

- **RTDE, port 30004** (protocol version 2, as in Universal Robots' RTDE guide): request
protocol version (``V``), get URControl version (``v``, answers an e-series 5.x), setup outputs
(``O``: every variable answered with its RTDE type, unknown names ``NOT_FOUND``), setup inputs
(``I``: recipes numbered from 1 per connection, a field set up by another connection
``IN_USE``), start (``S``), pause (``P``), data packages (``U``) both ways, big-endian, the
outputs at each recipe's frequency from a 500 Hz control loop.
"""

from __future__ import annotations

import asyncio
import logging
import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from sim.ur_controller.controller import CONTROLLER_VERSION, input_type, output_type

if TYPE_CHECKING:
    from sim.ur_controller.server import FakeServer

log = logging.getLogger("sim.ur_controller")


# -- RTDE package types (RTDE guide) -----------------------------------------------------------

RTDE_REQUEST_PROTOCOL_VERSION = 86  # 'V'
RTDE_GET_URCONTROL_VERSION = 118  # 'v'
RTDE_TEXT_MESSAGE = 77  # 'M'
RTDE_DATA_PACKAGE = 85  # 'U'
RTDE_CONTROL_PACKAGE_SETUP_OUTPUTS = 79  # 'O'
RTDE_CONTROL_PACKAGE_SETUP_INPUTS = 73  # 'I'
RTDE_CONTROL_PACKAGE_START = 83  # 'S'
RTDE_CONTROL_PACKAGE_PAUSE = 80  # 'P'

_HEADER = struct.Struct(">HB")

_TYPE_FORMATS = {
    "BOOL": "?",
    "UINT8": "B",
    "UINT32": "I",
    "UINT64": "Q",
    "INT32": "i",
    "DOUBLE": "d",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}
_TYPE_SIZES = {t: struct.calcsize(">" + f) for t, f in _TYPE_FORMATS.items()}

# -- RTDE server ---------------------------------------------------------------------------------


@dataclass
class _OutputRecipe:
    recipe_id: int
    names: list[str]
    getters: list[Callable[[], object]]
    packer: struct.Struct
    period_s: float
    next_t: float = 0.0


@dataclass
class _InputRecipe:
    recipe_id: int
    names: list[str]
    unpacker: struct.Struct
    vector: list[int]  # per field: number of values it takes from the unpacked tuple


class RTDESession(asyncio.Protocol):
    """One RTDE client connection."""

    def __init__(self, server: FakeServer) -> None:
        self.server = server
        self.ctl = server.controller
        self.buffer = bytearray()
        self.transport: asyncio.Transport | None = None
        self.outputs: list[_OutputRecipe] = []
        self.inputs: dict[int, _InputRecipe] = {}
        self.started = False
        self.peer = "?"
        self.owners = server.input_owners

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        host, port = transport.get_extra_info("peername")[:2]
        self.peer = f"{host}:{port}"
        self.server.rtde_sessions.add(self)
        log.debug("%s: RTDE connection from %s", self.ctl.name, self.peer)

    def connection_lost(self, exc: Exception | None) -> None:
        self.server.rtde_sessions.discard(self)
        for name, owner in list(self.owners.items()):
            if owner is self:
                del self.owners[name]
        log.debug("%s: RTDE connection from %s closed", self.ctl.name, self.peer)

    def send(self, kind: int, payload: bytes = b"") -> None:
        if self.transport is not None and not self.transport.is_closing():
            self.transport.write(_HEADER.pack(len(payload) + 3, kind) + payload)

    def data_received(self, data: bytes) -> None:
        self.buffer += data
        while len(self.buffer) >= 3:
            size, kind = _HEADER.unpack_from(self.buffer)
            if size < 3:
                log.warning("%s: RTDE package size %d from %s", self.ctl.name, size, self.peer)
                assert self.transport is not None
                self.transport.close()
                return
            if len(self.buffer) < size:
                return
            payload = bytes(self.buffer[3:size])
            del self.buffer[:size]
            try:
                self.handle(kind, payload)
            except Exception:
                log.exception("%s: RTDE package %r from %s", self.ctl.name, chr(kind), self.peer)

    def handle(self, kind: int, payload: bytes) -> None:
        if self.ctl.silent or (
            self.server.rtde_silent_after_handshake and kind != RTDE_REQUEST_PROTOCOL_VERSION
        ):
            return  # a silent controller reads and never answers
        if kind == RTDE_DATA_PACKAGE:
            self.data_package(payload)
            return
        self.server.record(f"rtde {chr(kind)} {self._describe(kind, payload)}")
        if kind == RTDE_REQUEST_PROTOCOL_VERSION:
            (version,) = struct.unpack(">H", payload[:2])
            self.send(kind, struct.pack(">B", 1 if version == 2 else 0))
        elif kind == RTDE_GET_URCONTROL_VERSION:
            self.send(kind, struct.pack(">IIII", *CONTROLLER_VERSION))
        elif kind == RTDE_CONTROL_PACKAGE_SETUP_OUTPUTS:
            self.setup_outputs(payload)
        elif kind == RTDE_CONTROL_PACKAGE_SETUP_INPUTS:
            self.setup_inputs(payload)
        elif kind == RTDE_CONTROL_PACKAGE_START:
            ok = bool(self.outputs) or bool(self.inputs)
            self.started = self.started or ok
            for recipe in self.outputs:
                recipe.next_t = self.ctl.t
            self.send(kind, struct.pack(">B", 1 if ok else 0))
        elif kind == RTDE_CONTROL_PACKAGE_PAUSE:
            self.started = False
            self.send(kind, struct.pack(">B", 1))
        elif kind == RTDE_TEXT_MESSAGE:
            log.info("%s: RTDE text message from %s: %r", self.ctl.name, self.peer, payload)
        else:
            log.warning("%s: unknown RTDE package type %d from %s", self.ctl.name, kind, self.peer)

    @staticmethod
    def _describe(kind: int, payload: bytes) -> str:
        if kind == RTDE_REQUEST_PROTOCOL_VERSION and len(payload) >= 2:
            return str(struct.unpack(">H", payload[:2])[0])
        if kind == RTDE_CONTROL_PACKAGE_SETUP_OUTPUTS and len(payload) >= 8:
            return f"{struct.unpack('>d', payload[:8])[0]:g} Hz {payload[8:].decode()}"
        if kind == RTDE_CONTROL_PACKAGE_SETUP_INPUTS:
            return payload.decode()
        return ""

    def setup_outputs(self, payload: bytes) -> None:
        (frequency,) = struct.unpack(">d", payload[:8])
        names = [n for n in payload[8:].decode().split(",") if n]
        types = [output_type(n) for n in names]
        ok = names and "NOT_FOUND" not in types and 0.0 < frequency <= 500.0
        recipe_id = len(self.outputs) + 1 if ok else 0
        if ok:
            fmt = ">B" + "".join(_TYPE_FORMATS[t] for t in types)
            self.outputs.append(
                _OutputRecipe(
                    recipe_id,
                    names,
                    [self.ctl.output_getter(n) for n in names],
                    struct.Struct(fmt),
                    1.0 / frequency,
                )
            )
        else:
            log.warning(
                "%s: output recipe refused (%g Hz): %s",
                self.ctl.name,
                frequency,
                [n for n, t in zip(names, types, strict=True) if t == "NOT_FOUND"],
            )
        self.send(RTDE_CONTROL_PACKAGE_SETUP_OUTPUTS, bytes([recipe_id]) + ",".join(types).encode())

    def setup_inputs(self, payload: bytes) -> None:
        names = [n for n in payload.decode().split(",") if n]
        types = []
        for n in names:
            t = input_type(n)
            owner = self.owners.get(n)
            types.append("IN_USE" if t != "NOT_FOUND" and owner not in (None, self) else t)
        ok = names and all(t in _TYPE_FORMATS for t in types)
        recipe_id = len(self.inputs) + 1 if ok else 0
        if ok:
            fmt = ">" + "".join(_TYPE_FORMATS[t] for t in types)
            counts = [int(_TYPE_FORMATS[t][:-1] or 1) for t in types]
            self.inputs[recipe_id] = _InputRecipe(recipe_id, names, struct.Struct(fmt), counts)
            for n in names:
                self.owners[n] = self
        else:
            log.warning(
                "%s: input recipe refused: %s", self.ctl.name, dict(zip(names, types, strict=True))
            )
        self.send(RTDE_CONTROL_PACKAGE_SETUP_INPUTS, bytes([recipe_id]) + ",".join(types).encode())

    def data_package(self, payload: bytes) -> None:
        if not payload:
            return
        recipe = self.inputs.get(payload[0])
        if recipe is None or len(payload) - 1 != recipe.unpacker.size:
            log.warning(
                "%s: data package for unknown recipe %d (%d bytes) from %s",
                self.ctl.name,
                payload[0],
                len(payload),
                self.peer,
            )
            return
        values = recipe.unpacker.unpack_from(payload, 1)
        i = 0
        for name, count in zip(recipe.names, recipe.vector, strict=True):
            value = values[i] if count == 1 else values[i : i + count]
            i += count
            self.ctl.set_input(name, value)

    def publish(self) -> None:
        """Send the data packages that are due at the controller's current time."""
        if self.ctl.silent or not self.started or self.transport is None:
            return
        if self.transport.is_closing():
            return
        if self.transport.get_write_buffer_size() > 1 << 20:
            return  # the client does not read: drop packages rather than buffer without end
        t = self.ctl.t
        for recipe in self.outputs:
            if t + 1e-9 < recipe.next_t:
                continue
            recipe.next_t += recipe.period_s
            if recipe.next_t <= t:
                recipe.next_t = t + recipe.period_s
            args: list[object] = [recipe.recipe_id]
            for getter in recipe.getters:
                value = getter()
                if isinstance(value, tuple):
                    args.extend(value)
                else:
                    args.append(value)
            self.send(RTDE_DATA_PACKAGE, recipe.packer.pack(*args))

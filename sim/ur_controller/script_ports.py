"""The fake controller's script ports (30001, 30002, 30003).

Script upload, ports 30001, 30002 and 30003: URScript text is accepted; a ``def`` program
replaces the running one. ur-rtde's control script (``def rtde_control():``) is not parsed
but emulated: the fake runs the script's register protocol in its control loop (below).
Other programs are only scanned for ``write_output_integer_register`` calls (which is what
ur-rtde's ``sendCustomScriptFunction`` waits on). Nothing is streamed back on these ports.
"""

from __future__ import annotations

import asyncio
import logging
import re
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from sim.ur_controller.server import FakeServer

log = logging.getLogger("sim.ur_controller")


# -- script ports --------------------------------------------------------------------------------

_PROGRAM_END = re.compile(r"^end[ \t]*(#[^\n]*)?(\n|\Z)", re.MULTILINE)


class ScriptSession(asyncio.Protocol):
    """One connection to a script port (30001/30002/30003): URScript text in, nothing out."""

    def __init__(self, server: FakeServer, port: int) -> None:
        self.server = server
        self.port = port
        self.text = ""

    def data_received(self, data: bytes) -> None:
        if self.server.controller.silent:
            return
        self.text += data.decode(errors="replace")
        while True:
            stripped = self.text.lstrip()
            if not stripped:
                self.text = ""
                return
            if re.match(r"(def|sec)\s", stripped):
                m = _PROGRAM_END.search(stripped)
                if m is None:
                    self.text = stripped
                    return  # wait for the rest of the program
                program, self.text = stripped[: m.end()], stripped[m.end() :]
                first = program.splitlines()[0]
                self.server.record(f"script:{self.port} {first} ... ({len(program)} chars)")
                self.server.controller.load_program(program)
            else:
                if "\n" not in stripped:
                    self.text = stripped
                    return
                line, self.text = stripped.split("\n", 1)
                self.server.record(f"script:{self.port} {line.strip()}")
                log.warning(
                    "%s: one-line script command not emulated: %s",
                    self.server.controller.name,
                    line.strip(),
                )

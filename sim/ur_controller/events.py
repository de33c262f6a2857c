"""Events of the fake controller that another process times against its own clock."""

from __future__ import annotations

import time


def print_event(name: str) -> None:
    """``EVENT <name> <time.monotonic()>`` on stdout (monotonic time is system-wide on Linux,
    so the process that started the fake compares it with its own clock)."""
    print(f"EVENT {name} {time.monotonic():.6f}", flush=True)

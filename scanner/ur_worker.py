"""The worker process that holds one arm's ur-rtde interfaces (:mod:`scanner.ur_client`).

Run as ``python scanner/ur_worker.py`` (by path: it imports nothing from this repository, so it
starts in the time Python and ur-rtde take to load). Requests come on stdin and answers go out
on the descriptor stdout had at start, as :mod:`multiprocessing.connection` messages; ur-rtde's
own console output is sent to stderr so that it cannot corrupt them.

Requests (tuples) and their answers, ``("ok", value)`` or ``("error", where, message)``:

- ``("open", host, frequency_hz, variables, upper_range_registers)``: construct
  ``RTDEReceiveInterface`` then ``RTDEControlInterface`` uploading its script (``where``
  "receive" or "control").
- ``("calls", [(interface, method, args), ...])``: call each in order on ``"receive"`` or
  ``"control"``; the list of results (an async-operation status as ``(operation_id,
  running)``).
- ``("close",)``: disconnect both interfaces, answer, exit.

End of input (the scanner exited or was killed) disconnects them and exits too. ur-rtde's
``disconnect`` closes an interface's sockets, then waits 0.5 s; both wait at once, and the
worker exits without running their destructors, which would call ``disconnect`` (and wait)
again.
"""

from __future__ import annotations

import os
import threading
from multiprocessing.connection import Connection
from typing import Any, NoReturn


def _plain(value: Any) -> Any:
    """A result as plain picklable data."""
    if hasattr(value, "operationId"):  # ur-rtde's AsyncOperationStatus
        return (int(value.operationId()), bool(value.isAsyncOperationRunning()))
    return value


def _open(interfaces: dict[str, Any], request: tuple) -> tuple:
    import rtde_control
    import rtde_receive

    _, host, frequency, variables, upper_range = request
    flags = rtde_control.RTDEControlInterface.FLAG_UPLOAD_SCRIPT
    if upper_range:
        flags |= rtde_control.RTDEControlInterface.FLAG_UPPER_RANGE_REGISTERS
    try:
        interfaces["receive"] = rtde_receive.RTDEReceiveInterface(
            host, frequency, variables, False, upper_range
        )
    except Exception as exc:
        return ("error", "receive", str(exc))
    try:
        interfaces["control"] = rtde_control.RTDEControlInterface(host, frequency, int(flags))
    except Exception as exc:
        interfaces.clear()
        return ("error", "control", str(exc))
    return ("ok", None)


def _calls(interfaces: dict[str, Any], request: tuple) -> tuple:
    results = []
    for interface, method, args in request[1]:
        try:
            results.append(_plain(getattr(interfaces[interface], method)(*args)))
        except Exception as exc:
            return ("error", f"{interface}.{method}", f"{type(exc).__name__}: {exc}")
    return ("ok", results)


def _disconnect(interfaces: dict[str, Any]) -> None:
    """Disconnect every interface, all at once."""
    threads = [threading.Thread(target=i.disconnect) for i in interfaces.values()]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()


def main() -> NoReturn:
    """Serve one arm's ur-rtde calls for the scanner process over the inherited pipes, then
    disconnect and exit (without the interfaces' destructors: they would disconnect, and
    wait, again)."""
    answers = Connection(os.dup(1), readable=False)
    os.dup2(2, 1)  # ur-rtde prints to stdout: keep it off the answer channel
    requests = Connection(os.dup(0), writable=False)
    interfaces: dict[str, Any] = {}
    closing = False
    while not closing:
        try:
            request = requests.recv()
        except (EOFError, OSError):
            break
        op = request[0]
        if op == "close":
            closing = True
        elif op == "open":
            answers.send(_open(interfaces, request))
        elif op == "calls":
            answers.send(_calls(interfaces, request))
        else:
            answers.send(("error", op, f"unknown request {op!r}"))
    _disconnect(interfaces)
    if closing:
        answers.send(("ok", None))
    os._exit(0)


if __name__ == "__main__":
    main()

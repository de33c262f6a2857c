"""The operator's stop (scanner.stop): real signals sent to this process set the request, the
watchdog acts while the main thread is stuck in a call that does not return, and nothing is
commanded once the request is set."""

from __future__ import annotations

import os
import signal
import sys
import threading
import time

import pytest

from scanner.stop import GRACE_S, STOP_SIGNALS, OperatorStop, StopRequest, stop_signals

SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT)


@pytest.mark.parametrize("sig", SIGNALS, ids=lambda s: s.name)
def test_a_stop_signal_sets_the_request_and_is_not_raised_while_deferring(sig):
    stop = StopRequest()
    with stop_signals(stop), stop.deferring():
        try:  # a try that swallows everything: the request is still set
            os.kill(os.getpid(), sig)
            time.sleep(0.01)  # the handler runs in this thread, at the next bytecode
        except BaseException:
            pytest.fail("the handler raised inside deferring()")
        assert stop.is_set and stop.signum == sig
        assert sig.name in stop.reason
        with pytest.raises(OperatorStop, match=f"stopped by {sig.name}.*: EXP not sent"):
            stop.check("EXP")
    assert signal.getsignal(sig) is not stop._handle_signal  # the previous handler is back


def test_outside_deferring_a_stop_signal_raises_like_ctrl_c():
    stop = StopRequest()
    with stop_signals(stop), pytest.raises(KeyboardInterrupt, match="stopped by SIGTERM"):
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(1.0)
    assert stop.is_set


def test_a_wait_for_the_operator_is_ended_by_a_stop_signal_even_while_deferring():
    stop = StopRequest()
    with stop_signals(stop), stop.deferring():
        with pytest.raises(OperatorStop), stop.interrupting():
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1.0)
        with pytest.raises(OperatorStop), stop.interrupting():  # set already: at once
            pytest.fail("entered a wait after the stop")


def test_the_switch_interval_and_handlers_are_restored():
    before = {sig: signal.getsignal(sig) for sig in SIGNALS}
    interval = sys.getswitchinterval()
    with stop_signals(StopRequest()):
        assert sys.getswitchinterval() <= 0.001
    assert sys.getswitchinterval() == interval
    assert {sig: signal.getsignal(sig) for sig in SIGNALS} == before


def test_the_watchdog_acts_while_the_main_thread_is_stuck_in_a_call():
    """The main thread waits in a lock acquire (a call that retries after the handler, as a
    blocking device call does): the guard's action runs on the watchdog within its grace plus
    scheduling, long before the call returns; once the loop acknowledges, it stays done once."""
    stop = StopRequest()
    ran: list[tuple[float, str]] = []
    stuck = threading.Lock()
    stuck.acquire()
    with stop_signals(stop), stop.deferring():
        with stop.guarding(lambda: ran.append((time.monotonic(), threading.current_thread().name))):
            t0 = time.monotonic()
            os.kill(os.getpid(), signal.SIGHUP)
            stuck.acquire(timeout=0.5)  # never released: the whole 0.5 s
            t1 = time.monotonic()
    assert len(ran) == 1, ran
    ((t_action, thread),) = ran
    assert thread == "stop-watchdog"
    assert GRACE_S <= t_action - t0 < 0.1 and t_action < t1 - 0.3


def test_an_acknowledged_stop_is_left_to_the_loop():
    stop = StopRequest()
    ran = []
    with stop_signals(stop), stop.deferring(), stop.guarding(lambda: ran.append(1)) as guard:
        guard.acknowledge()
        stop.set("test")
        time.sleep(10 * GRACE_S)
    assert ran == []


def test_no_command_is_sent_after_the_watchdog_stops():
    """A command under way when the stop comes finishes before the watchdog's stop; every
    command after the request is refused before it is sent."""
    stop = StopRequest()
    log: list[str] = []
    started = threading.Event()

    def loop() -> None:
        with stop.deferring():
            try:
                while True:
                    with stop.commanding("set-point"):
                        log.append("command")
                        started.set()
                        time.sleep(3 * GRACE_S)  # a slow round trip
                        log.append("command done")
            except OperatorStop:
                log.append("refused")

    with stop_signals(stop), stop.guarding(lambda: log.append("stop")):
        worker = threading.Thread(target=loop)
        worker.start()
        started.wait()
        stop.set("test")
        worker.join()
    i = log.index("stop")  # after the command under way, and no command after it
    assert log[:i].count("command") == log[:i].count("command done") >= 1
    assert "command" not in log[i:] and log[-1] in ("refused", "stop")


def test_a_request_names_each_stop_signal():
    for sig, words in STOP_SIGNALS.items():
        assert words.startswith(sig.name)

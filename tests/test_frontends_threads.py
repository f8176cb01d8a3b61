"""`frontends.threads`: `replay --map`'s second tracker runs beside the first, in order."""

from __future__ import annotations

import threading
import time
from functools import partial

import pytest

from frontends.threads import InOrderWorker


def test_calls_run_in_the_order_given_on_another_thread() -> None:
    ran: list[tuple[int, str]] = []
    worker = InOrderWorker("test", threaded=True)

    def call(k: int) -> None:
        time.sleep(0.002 if k < 5 else 0.0)  # early calls slower: the order comes from the queue
        ran.append((k, threading.current_thread().name))

    for k in range(50):
        worker.submit(partial(call, k))
    worker.drain()
    assert [k for k, _ in ran] == list(range(50))
    assert all(name != threading.current_thread().name for _, name in ran)


def test_a_failure_is_raised_by_the_next_submit_and_later_calls_do_not_run() -> None:
    ran: list[int] = []
    started, release = threading.Event(), threading.Event()
    worker = InOrderWorker("test", max_pending=4, threaded=True)

    def fail() -> None:
        started.set()
        release.wait(5.0)
        raise ValueError("bad scan")

    worker.submit(fail)
    started.wait(5.0)
    worker.submit(lambda: ran.append(1))  # queued behind the failing call, which has not failed yet
    release.set()
    with pytest.raises(ValueError, match="bad scan"):
        for _ in range(10):  # the failure surfaces once the call is done (the queue is full by then)
            worker.submit(lambda: ran.append(2))
    assert ran == []
    worker.drain()  # the calls behind the failure were skipped, not failed
    assert ran == []


def test_drain_raises_a_failure_of_the_last_calls() -> None:
    worker = InOrderWorker("test", threaded=True)
    worker.submit(lambda: None)
    worker.submit(lambda: 1 / 0)
    with pytest.raises(ZeroDivisionError):
        worker.drain()


def test_submit_waits_once_max_pending_calls_are_queued() -> None:
    release = threading.Event()
    worker = InOrderWorker("test", max_pending=2, threaded=True)
    worker.submit(lambda: release.wait(5.0))
    worker.submit(lambda: None)
    submitted = threading.Event()

    def third() -> None:
        worker.submit(lambda: None)
        submitted.set()

    caller = threading.Thread(target=third)
    caller.start()
    assert not submitted.wait(0.2)  # bounded: the third waits for the first to finish
    release.set()
    assert submitted.wait(5.0)
    caller.join()
    worker.drain()


def test_on_one_core_each_call_runs_at_once_in_the_caller() -> None:
    ran: list[str] = []
    worker = InOrderWorker("test", threaded=False)
    worker.submit(lambda: ran.append(threading.current_thread().name))
    assert ran == [threading.current_thread().name]  # before any drain
    with pytest.raises(ZeroDivisionError):
        worker.submit(lambda: 1 / 0)
    worker.drain()


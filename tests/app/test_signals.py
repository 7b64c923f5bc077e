"""Signals after SLAM: noted in the main thread, left alone in any other (a Ray actor's)."""

from __future__ import annotations

import os
import signal
import threading

from pipeline.app.signals import signals_noted


def test_a_signal_inside_is_noted_and_the_handler_before_comes_back() -> None:
    before = signal.getsignal(signal.SIGTERM)
    with signals_noted() as noted:
        os.kill(os.getpid(), signal.SIGTERM)
        assert noted.wait(5)
    assert signal.getsignal(signal.SIGTERM) is before


def test_outside_the_main_thread_nothing_is_installed() -> None:
    """Python refuses signal handlers off the main thread: a serve session in a Ray actor runs
    there, and must not fail for it."""
    seen: list[object] = []

    def session() -> None:
        try:
            with signals_noted() as noted:
                seen.append(noted.is_set())
        except ValueError as exc:  # "signal only works in main thread"
            seen.append(exc)

    worker = threading.Thread(target=session)
    worker.start()
    worker.join(10)
    assert seen == [False]


def test_a_second_signal_calls_on_again_and_a_third_too() -> None:
    """The first signal is noted (the final refinement and the evaluation are cut short); each
    later one calls on_again (SLAM then waits for nothing more and saves what is complete)."""
    again: list[int] = []
    with signals_noted(on_again=lambda: again.append(1)) as noted:
        os.kill(os.getpid(), signal.SIGINT)
        assert noted.wait(5) and again == []
        os.kill(os.getpid(), signal.SIGTERM)
        os.kill(os.getpid(), signal.SIGINT)
    assert again == [1, 1]

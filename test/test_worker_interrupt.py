"""SolveWorker.interrupt (core/nlp/worker.py), offline: a solve that only its deadline would end is
abandoned at once when a signal handler interrupts the worker (Python retries the select() a
signal interrupts, so the wait also watches the worker's wakeup pipe); calls stay abandoned until
`resume`, then the worker serves again. What the nodes rely on for SIGINT and lifecycle
transitions mid-solve (test_interrupt_dds)."""

from __future__ import annotations

import signal
import threading
import time

import numpy as np
import pytest
from test_interrupt_dds import LONG_REGIONS, LONG_SOLVE_TIME, LONG_STATE

from nmpc_avoid_ros.core.config.settings import ControllerSettings, default_config_path, load_params_file
from nmpc_avoid_ros.core.nlp.worker import ABANDONED
from nmpc_avoid_ros.core.sample.controller import NmpcController

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def controller() -> NmpcController:
    params = load_params_file(default_config_path()).section("controller")
    return NmpcController(ControllerSettings.from_params(params).replace(max_solve_time=LONG_SOLVE_TIME))


def abandoned(result) -> list[str]:
    return [t.label for t in result.search.tried if t.solver_status == ABANDONED]


def test_a_signal_handler_interrupts_a_solve_that_runs_to_its_deadline(controller):
    worker = controller.worker
    controller.reset()
    controller.set_regions(LONG_REGIONS)
    previous = signal.signal(signal.SIGALRM, lambda *_: worker.interrupt())
    signal.setitimer(signal.ITIMER_REAL, 1.0)  # 1 s into the step: inside the call that loops (offline: ~40 s)
    try:
        begin = time.perf_counter()
        result = controller.step(LONG_STATE, [5.0])
        took = time.perf_counter() - begin
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
    # the rest of the sample: the fallback's recovery solve, in process (IPOPT, 0.2 max_solve_time at most)
    assert took < 1.0 + 0.2 * LONG_SOLVE_TIME, (took, result.search.render())
    assert abandoned(result) and result.is_fallback and np.all(np.isfinite(result.u))
    assert worker.interrupted
    begin = time.perf_counter()
    again = controller.step(LONG_STATE, [5.0])  # still interrupted: no solver call waits
    assert time.perf_counter() - begin < 0.2 * LONG_SOLVE_TIME + 0.5 and np.all(np.isfinite(again.u))
    worker.resume()
    controller.reset()
    controller.set_regions([])
    served = controller.step([0.5, 0.0], [1.0])
    assert served.status == "ok" and not abandoned(served), served.search.render()


def test_interrupt_from_another_thread_and_a_stale_wakeup_byte_does_not_abandon_later_calls(controller):
    worker = controller.worker
    controller.reset()
    controller.set_regions(LONG_REGIONS)
    timer = threading.Timer(1.0, worker.interrupt)
    timer.start()
    begin = time.perf_counter()
    result = controller.step(LONG_STATE, [5.0])
    assert time.perf_counter() - begin < 1.0 + 0.2 * LONG_SOLVE_TIME and abandoned(result)
    worker.resume()
    # interrupt() and resume() racing can leave a byte in the wakeup pipe with the worker serving:
    # the wait drains it and goes on waiting for the answer
    worker.interrupt()
    # private: no public call leaves this race's state (a stale wakeup byte with the flag cleared)
    worker._interrupted = False  # what a resume() between interrupt's flag and its write leaves
    controller.reset()
    controller.set_regions([])
    served = controller.step([0.5, 0.0], [1.0])
    assert served.status == "ok" and not abandoned(served), served.search.render()

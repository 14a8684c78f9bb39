"""A first start in seconds (issue 31 item 4): with codegen_background, an empty solver cache serves
with interpreted solvers at once while the libraries compile in a background process, and the
compiled solvers are swapped in between samples (core/nlp/background.py, core/nlp/worker.py).

The compile is held until the test releases it, so which solver answers is not a race. Speed numbers
are not tested here (test/test_first_start_dds.py holds the node's first command to a generous bound).
"""

from __future__ import annotations

import logging
import threading
import time

import numpy as np
import pytest

from nmpc_avoid_ros.core.config.settings import ControllerSettings
from nmpc_avoid_ros.core.nlp import background
from nmpc_avoid_ros.core.nlp.tracking import TrackingNlp
from nmpc_avoid_ros.core.sample.controller import NmpcController
from nmpc_avoid_ros.core.sample.status import StepStatus

#: the paper's problem on the real-time path without obstacle slots: 2 libraries (FATROP's, the IPOPT reference's)
FAST = ControllerSettings(max_ellipses=0, max_polygons=0, solver="fatrop", codegen=True, codegen_background=True)
X0, TARGET = np.array([-5.0, 0.0]), np.array([5.0])
#: s from the start of the construction to the first step's answer, the compile held (generous: a loaded CI machine)
FIRST_STEP_BOUND = 10.0


@pytest.fixture
def held(monkeypatch):
    """The background compiles wait until `held.set()` (set at the end of the test in any case)."""
    release, real = threading.Event(), background._compile_in_child

    def wait_then_compile(job):
        release.wait()
        return real(job)

    # patched: no seam holds a compile back, and the interpreted phase must be observed for certain
    monkeypatch.setattr(background, "_compile_in_child", wait_then_compile)
    yield release
    release.set()
    background.wait_compiled(120.0)


def test_an_empty_cache_serves_interpreted_at_once_and_swaps_the_compiled_in_between_samples(tmp_path, held,
                                                                                           caplog):
    caplog.set_level(logging.INFO, logger="nmpc_avoid_ros")
    settings = FAST.replace(cache_dir=str(tmp_path))
    begin = time.perf_counter()
    controller = NmpcController(settings)
    info = controller.nlp.solver_info
    assert info["background"] and info["cache_hit"] is False and info["codegen"]
    first = controller.step(X0, TARGET)
    assert time.perf_counter() - begin < FIRST_STEP_BOUND
    assert first.status == StepStatus.OK
    worker = controller.worker
    assert background.compiling() == 2 and not list(tmp_path.glob("*.so"))  # held: interpreted solvers answered
    assert worker.forks == 1 and worker.swaps == 0
    builds = controller.nlp_builds

    held.set()
    assert background.wait_compiled(120.0)
    assert len(list(tmp_path.glob("*.so"))) == 2
    for nlp in (controller.nlp, controller.cold_nlp):
        assert background.current(nlp.solver) is not nlp.solver  # loaded, swapped in at the next sample
    second = controller.step(first.states[1], TARGET)
    assert second.status == StepStatus.OK
    assert worker.swaps == 1 and worker.forks == 2  # the child holding the interpreted solvers was replaced
    assert controller.nlp_builds == builds  # the same solvers, compiled: no new build
    swapped = [r.getMessage() for r in caplog.records if "swapped in between samples" in r.getMessage()]
    assert swapped and "all compiled solvers in use" in swapped[-1], swapped
    assert sorted(p.suffix for p in tmp_path.iterdir()) == [".so", ".so"]  # no job file, no build folder left

    # the compiled solvers agree with the interpreted ones on the same inputs, to the solver's tolerance
    again = NmpcController(settings)
    assert again.nlp.solver_info["cache_hit"] is True and not again.nlp.solver_info["background"]
    compiled = again.step(X0, TARGET)
    np.testing.assert_allclose(compiled.states, first.states, atol=1e-6)
    np.testing.assert_allclose(compiled.inputs, first.inputs, atol=1e-6)


def test_a_solve_without_worker_swaps_at_its_next_call_and_agrees(tmp_path, held):
    nlp = TrackingNlp(FAST.replace(solver="ipopt", cache_dir=str(tmp_path)))
    n_w, n_g = nlp.layout.n_w, nlp.lbg.size
    par = nlp.parameters(X0, TARGET, np.zeros(nlp.slot_layout.size), kappa=1e4, mu=1e8,
                         state_weights=np.ones(2), input_weights=np.ones(1),
                         keep_in_active=np.ones(nlp.layout.n_keep_in))
    guess = np.zeros(n_w)
    interpreted = nlp.solve(guess, par, np.zeros(n_w), np.zeros(n_g))
    assert background.current(nlp.solver) is nlp.solver  # solved interpreted: nothing compiled yet
    held.set()
    assert background.wait_compiled(120.0)
    compiled = nlp.solve(guess, par, np.zeros(n_w), np.zeros(n_g))
    assert background.current(nlp.solver) is not nlp.solver  # solved by its compiled twin
    assert interpreted[3]["return_status"] == compiled[3]["return_status"] == "Solve_Succeeded"
    np.testing.assert_allclose(compiled[0], interpreted[0], atol=1e-6)


def test_a_failed_background_compile_keeps_the_interpreted_solver(tmp_path, monkeypatch, caplog):
    caplog.set_level(logging.WARNING, logger="nmpc_avoid_ros")
    monkeypatch.setenv("CC", "false")  # a "compiler" that exists and always fails
    nlp = TrackingNlp(FAST.replace(solver="ipopt", cache_dir=str(tmp_path)))
    assert background.wait_compiled(120.0)
    assert background.current(nlp.solver) is nlp.solver and not list(tmp_path.glob("*.so"))
    assert any("failed: the interpreted solver stays in use" in r.getMessage() for r in caplog.records)
    assert [p for p in tmp_path.iterdir()] == []  # the failed build and its job file are gone


def test_a_compiler_killed_mid_build_leaves_its_temporary_files_nowhere(tmp_path, monkeypatch):
    """gcc writes its assembler file to $TMPDIR (ccXXXXXX.s) and removes it on exit, not when it is killed
    (SIGKILL: the compile of a stopping controller, core/nlp/codegen.py `_compile`). The compiler's TMPDIR is the
    build's own temporary folder, removed with it; /tmp had gathered 102 such files here."""
    import casadi as ca

    from nmpc_avoid_ros.core.errors import ConfigError
    from nmpc_avoid_ros.core.nlp.codegen import compiled_function

    made = tmp_path / "made.txt"
    compiler = tmp_path / "cc"  # writes a temporary file as gcc does, then dies as a killed one
    compiler.write_text(f'#!/bin/sh\nmktemp > {made}\nkill -9 $$\n')
    compiler.chmod(0o755)
    monkeypatch.setenv("CC", str(compiler))
    x = ca.SX.sym("x")
    cache = tmp_path / "cache"
    with pytest.raises(ConfigError, match="failed"):
        compiled_function(ca.Function("square", [x], [x * x]), cache)
    left = made.read_text().strip()
    assert left.startswith(str(cache)), left  # written in the build's folder, not /tmp
    assert not (cache / left).exists() and list(cache.iterdir()) == []

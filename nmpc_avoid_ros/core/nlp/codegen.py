"""Generated and compiled NLP oracles, cached on disk by a hash of the problem structure.

CasADi writes the functions a solver evaluates (cost, constraints and their derivatives) as C
(`generate_dependencies`); compiled into a shared library they run several times faster than
CasADi's virtual machine, and `nlpsol(name, plugin, "lib.so", opts)` loads them without any
symbolic work. The cache key is a SHA-256 of the CasADi version, the solver plugin and the
serialised symbolic problem, so any change of structure (horizon, model, region capacity, ...)
gets its own library, and run-time parameters (target, weights, obstacles) never do.

A first start compiles (nothing in the cache for this structure): the first compile of a process
logs once, on the `logging` logger of this module, that it compiles, about how long it takes and
where the cache is; the nodes pass core's log records on to the ROS log (nodes/runner.py). With the
setting codegen_background: true the compile runs in a background process while interpreted solvers
serve (core/nlp/background.py `interpreted_while_compiling`); by default here, before the
constructor returns.
"""

from __future__ import annotations

import hashlib
import logging
import os
import shutil
import signal
import subprocess
import tempfile
from collections.abc import Callable
from pathlib import Path

import casadi as ca

from ..errors import ConfigError
from .native_threads import scratch, start_native

#: environment variable that overrides the default cache folder
CACHE_ENV = "NMPC_AVOID_ROS_CACHE"
#: the compiler's flags. No optimisation: the generated sources are large (0.1-2 MB of C for one
#: NLP) and gcc's optimiser is slow on them, while the solver's own linear algebra is compiled
#: already. Measured (gcc 12, the mobile robot's 4-ellipse NLP at N = 20, 980 kB): -O0 1.9 s,
#: -O1 7.4 s, -O2 12.9 s to compile; solves 12 % slower than -O2 (robot), 6 % (van der Pol). A
#: shipped config's first start compiles 9 s (van der Pol) and 16 s (robot) instead of 44 and 77.
COMPILE_FLAGS = ("-O0", "-fPIC", "-shared")
#: s to generate and compile one NLP's code on a 2-core machine, and how many NLPs a shipped live
#: config compiles at most (config/van_der_pol_live.yaml: 6, its first start took 77 s here): what the
#: first start's log line announces.
SECONDS_PER_NLP = 13.0
LIVE_CONFIG_NLPS = 6

log = logging.getLogger(__name__)
_announced = False  # the first compile of this process logged


def announce_compile(folder: Path, background: bool = False) -> None:
    """Log once per process that a compile starts, about how long it takes and where the cache is
    (`background`: and that interpreted solvers serve until the compiled ones are swapped in)."""
    global _announced
    if _announced:
        return
    _announced = True
    where = (" in the background while interpreted solvers (the same NLPs, solved slower) serve; each compiled one "
             "is swapped in between samples once ready" if background else "")
    log.info(f"first start with this problem structure: compiling the solver's generated code{where}, up to about "
             f"{SECONDS_PER_NLP:.0f} s per NLP (a shipped live config compiles up to {LIVE_CONFIG_NLPS}: about "
             f"{SECONDS_PER_NLP * LIVE_CONFIG_NLPS / 60:.1f} min on 2 cores); cached in {folder}: later starts "
             f"load it at once")


def cache_dir(setting: str = "") -> Path:
    """The cache folder: the setting, else $NMPC_AVOID_ROS_CACHE, else $XDG_CACHE_HOME/nmpc_avoid_ros."""
    if setting:
        return Path(setting).expanduser()
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV]).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "nmpc_avoid_ros"


def structure_hash(plugin: str, nlp: dict) -> str:
    """SHA-256 (hex, 16 chars) of the CasADi version, the plugin, the compiler flags and the symbolic problem."""
    return problem_digest(nlp, plugin, " ".join(COMPILE_FLAGS))


def problem_digest(nlp: dict, *parts: str | bytes) -> str:
    """SHA-256 (hex, 16 chars) of the CasADi version, `parts` and the serialised symbolic problem (w, p) -> (f, g) of
    `nlp` (its keys x, p, f, g): the name of what a cache keeps for that problem (a solver library, the feedback law's
    derivatives, core/nlp/sensitivity.py)."""
    problem = ca.Function("nlp", [nlp["x"], nlp["p"]], [nlp["f"], nlp["g"]])
    digest = hashlib.sha256()
    for part in (ca.__version__, *parts, problem.serialize()):
        digest.update(part.encode() if isinstance(part, str) else part)
    return digest.hexdigest()[:16]


def library_path(key: str, folder: Path) -> Path:
    """Where the library of the structure `key` is cached."""
    return folder / f"nmpc_{key}.so"


def prepare_folder(folder: Path) -> str:
    """The compiler ($CC, default cc), after checking that it exists and that `folder` can be created."""
    compiler = os.environ.get("CC", "cc")
    if shutil.which(compiler) is None:
        raise ConfigError(f"codegen needs a C compiler ({compiler!r} not found): install gcc, set CC, "
                          "or set codegen: false")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"cannot create the solver cache folder {folder}: {exc.strerror or exc}") from None
    return compiler


def function_library(function: ca.Function, folder: Path) -> Path:
    """Where `compiled_function` caches the library of `function`."""
    digest = hashlib.sha256()
    for part in (ca.__version__, " ".join(COMPILE_FLAGS), function.serialize()):
        digest.update(part.encode())
    return folder / f"{function.name()}_{digest.hexdigest()[:16]}.so"


def compiled_function(function: ca.Function, folder: Path) -> ca.Function:
    """`function` generated as C, compiled (COMPILE_FLAGS) and loaded, cached in `folder` by a SHA-256 of the CasADi
    version, the flags and the serialised function. For a small Function on a latency-critical path (the feedback
    law's feasibility test, core/sample/feedback.py: 19 us compiled against 42 us interpreted, the live van der
    Pol NLP); compiled at once on a miss (about a second)."""
    library, name = function_library(function, folder), function.name()
    if not library.exists():
        compiler = prepare_folder(folder)
        with tempfile.TemporaryDirectory(dir=folder) as tmp, scratch(Path(tmp)):
            # written under a prefix, not the working directory: threads compile these at once (a first start
            # compiles one per feedback law in the background), and a chdir is the whole process's
            generator = ca.CodeGenerator(f"{name}.c")
            generator.add(function)
            generator.generate(f"{tmp}{os.sep}")
            built = Path(tmp) / f"{name}.so"
            returncode, stderr = _compile(compiler, Path(tmp) / f"{name}.c", built, own_group=False)
            if returncode != 0:
                raise ConfigError(f"compiling the generated {name} failed: {stderr.strip()[:500]}")
            os.replace(built, library)
    return ca.external(name, str(library))


def serve_compiled(function: ca.Function, folder: Path | None, background: bool, install: Callable[[ca.Function], None],
                   what: str) -> None:
    """`install` the Function that serves for `function`: itself without a cache `folder`; else compiled
    (`compiled_function`), at once, or with `background` and nothing in the cache, the interpreted one now and the
    compiled one from a thread once built (a first start waits for nothing, as the solvers with codegen_background).
    A failed compile leaves the interpreted one serving, with a warning naming `what`."""
    if folder is None:
        install(function)
        return
    if not background or function_library(function, folder).exists():
        install(compiled_function(function, folder))
        return
    install(function)

    def compile_and_install() -> None:
        try:
            install(compiled_function(function, folder))
        except ConfigError as error:  # as a failed solver compile: the interpreted one serves on
            log.warning(f"{what} stays interpreted: {error}")

    start_native(compile_and_install, name=f"{function.name()}-compile")


def compiled_library(key: str, folder: Path, make_solver: Callable[[], ca.Function],
                     own_group: bool = False) -> tuple[Path, bool]:
    """Path of the compiled oracle library for `key` and whether it came from the cache.

    On a miss, `make_solver()` builds the symbolic solver whose oracles are generated and compiled
    with $CC (default cc) and COMPILE_FLAGS; the library is moved into place atomically, so concurrent
    processes never load a half-written file (a caller with a background compile of the same library in
    flight waits for it first: core/nlp/background.py `pending`). `own_group`: the compiler runs
    in a process group of its own, killed when this call ends by an exception (the background compile
    process, whose compiler would otherwise outlive it when the process that started it ends).
    """
    library = library_path(key, folder)
    if library.exists():
        return library, True
    compiler = prepare_folder(folder)
    announce_compile(folder)
    solver = make_solver()
    with tempfile.TemporaryDirectory(dir=folder) as tmp:
        source = f"nmpc_{key}.c"
        cwd = os.getcwd()
        os.chdir(tmp)  # generate_dependencies writes into the working directory
        try:
            solver.generate_dependencies(source)
        finally:
            os.chdir(cwd)
        built = Path(tmp) / f"nmpc_{key}.so"
        returncode, stderr = _compile(compiler, Path(tmp) / source, built, own_group)
        if returncode != 0:
            raise ConfigError(f"compiling the generated solver failed (exit status {returncode}): "
                              f"{stderr.strip()[:500]}")
        os.replace(built, library)
    return library, False


def _compile(compiler: str, source: Path, built: Path, own_group: bool) -> tuple[int, str]:
    """Run the compiler; (exit status, stderr). An exception while it runs (SystemExit from a signal
    handler, KeyboardInterrupt) kills it, with its group when it has its own (the driver's cc1 too).
    Its temporary files go to the source's folder (TMPDIR), removed with it: a compiler killed mid-build
    leaves its assembler file behind (gcc's ccXXXXXX.s), and in /tmp 102 of them had gathered here."""
    env = {**os.environ, "TMPDIR": str(source.parent)}
    proc = subprocess.Popen([compiler, *COMPILE_FLAGS, str(source), "-o", str(built)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=own_group, env=env)
    try:
        _, stderr = proc.communicate()
    finally:
        if proc.poll() is None:
            try:
                os.killpg(proc.pid, signal.SIGKILL) if own_group else proc.kill()
            except ProcessLookupError:
                pass
            proc.wait()
    return proc.returncode, stderr

"""Test-session configuration: float64 available and strict dtype promotion (DESIGN.md)."""

import gc
import os

os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
# JAX's persistent compilation cache for the test session, shared by the xdist workers and the
# subprocesses that tests start (they inherit the environment): a program compiled once, by any
# of them, is loaded rather than compiled again (after a cache clear below, by the other worker,
# in a later run). Under the checkout's ignored .cache/, so a clean clone starts empty, as CI does.
_CACHE_DIR = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), ".cache", "jax-tests")
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", _CACHE_DIR)
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")

# Flags of XLA's CPU compiler that cut compile time without changing what a program computes
# (compiling is the suite's cost):
# - its MLIR fusion emitters are the default; the classic elemental emitter compiles the same HLO
#   (same semantics, no fast math) in about half the time (measured on the suite's combined
#   transform programs);
# - it splits each program's LLVM module into parts for parallel code generation; with two
#   workers on two cores there is no core to spare, and the split parts cost about 12% more CPU
#   time than one module (measured on the same programs, two processes side by side).
_FAST_COMPILE_FLAGS = ("--xla_cpu_use_fusion_emitters=false", "--xla_cpu_parallel_codegen_split_count=1")


def _xla_knows(flag: str) -> bool:
    """Whether this jaxlib's XLA accepts ``flag`` (an unknown XLA flag aborts the process).

    Asked once per jaxlib version, in a subprocess, and remembered under the cache directory.
    """
    import importlib.metadata
    import subprocess
    import sys

    version = importlib.metadata.version("jaxlib")
    verdict = os.path.join(_CACHE_DIR, f"xla-flag-{flag.strip('-').replace('=', '-')}-jaxlib-{version}")
    for answer in ("yes", "no"):
        if os.path.exists(f"{verdict}.{answer}"):
            return answer == "yes"
    env = {**os.environ, "XLA_FLAGS": flag, "JAX_PLATFORMS": "cpu"}
    probe = subprocess.run([sys.executable, "-c", "import jax; jax.devices()"], env=env, capture_output=True, timeout=120)
    answer = "yes" if probe.returncode == 0 else "no"
    os.makedirs(_CACHE_DIR, exist_ok=True)
    open(f"{verdict}.{answer}", "w").close()
    return answer == "yes"


for _flag in _FAST_COMPILE_FLAGS:
    if _flag.split("=")[0] not in os.environ.get("XLA_FLAGS", "") and _xla_knows(_flag):
        # Set before JAX creates its CPU client; inherited by the subprocesses that tests start.
        os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {_flag}".strip()

import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")
# Compiling, not running, is the suite's cost: its programs are small and each runs a few times.
# XLA's cheap optimisation level (fewer HLO simplifications, LLVM without its expensive passes;
# IEEE semantics, no fast math, so results may differ from the optimised program's only by
# rounding) cuts every compile. The subprocesses that tests start (examples, sharding) use it too;
# CI's README demo and wheel check (.ci/run) compile at the default level, so optimised programs
# are exercised on every landing.
# Known hazard: jaxlib 0.10's CPU backend miscompiled one program under this pair of settings
# (classic emitter at optimisation level 0): a jitted gather + closest point on a triangle + norm
# returned 0.898 for one of 150 points whose distance is 3e-16; either setting alone, or the
# classic emitter at --xla_backend_optimization_level=1, gave the right answer. Those safe
# configurations doubled the suite's compile time (measured: 1,197 s against 601 s), so the pair
# stays, and a test that fails only here is checked against a default-flag run before its code.
jax.config.update("jax_disable_most_optimizations", True)


def _has_gpu() -> bool:
    try:
        return any(d.platform == "gpu" for d in jax.devices())
    except RuntimeError:
        return False


@pytest.hookimpl(tryfirst=True)  # before ``-m`` deselects by marker
def pytest_collection_modifyitems(config, items):
    # The quick tier (tests/quick_tier.py): mark the tests it names with the op and kind they cover.
    from tests.quick_tier import quick_tests

    quick = quick_tests()
    for item in items:
        for op, kind in quick.get(item.nodeid, ()):
            item.add_marker(pytest.mark.quick(op=op, kind=kind))
    if _has_gpu():
        return
    skip = pytest.mark.skip(reason="needs a CUDA device")
    for item in items:
        if "gpu" in item.keywords:
            item.add_marker(skip)


def _memory_map_count() -> int:
    try:
        with open("/proc/self/maps", "rb") as maps:
            return maps.read().count(b"\n")
    except OSError:  # not Linux: no per-process map limit to watch
        return 0


def _memory_map_limit() -> int:
    try:
        with open("/proc/sys/vm/max_map_count") as limit:
            return int(limit.read())
    except (OSError, ValueError):
        return 65530


def _resident_bytes() -> int:
    try:
        with open("/proc/self/statm") as statm:
            return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return 0


# Compiled programs are dropped once the process holds half of the kernel's mapping limit, or
# 4 GiB resident (two workers on a 24 GiB machine, with room for the subprocesses they start).
_MAP_BUDGET = _memory_map_limit() // 2
_RESIDENT_BUDGET = 4 * 2**30
# Memory that clearing does not give back (allocator arenas, torch, Warp) must not make every
# later test clear again: after a clear, the next one waits until the process has grown by this
# much past the level the clear left it at (each clear costs every later test its programs).
_REGROWTH = {"maps": _MAP_BUDGET // 4, "resident": 2**30}
_AFTER_LAST_CLEAR = {"maps": 0, "resident": 0}
# Reading /proc/self/maps costs about 1 ms per 1,000 mappings (34 ms at 30,000), so the count is
# read again only after this many new executables, each of which adds a few mappings: far below
# the headroom between the budget and the limit.
_MAP_READ_EVERY = 100
_LAST_MAP_READING = {"maps": 0, "programs": -_MAP_READ_EVERY}


def _recent_memory_map_count() -> int:
    if _COMPILES["programs"] - _LAST_MAP_READING["programs"] >= _MAP_READ_EVERY:
        _LAST_MAP_READING.update(maps=_memory_map_count(), programs=_COMPILES["programs"])
    return _LAST_MAP_READING["maps"]


@pytest.fixture(autouse=True)
def _release_compiled_executables_when_near_a_limit():
    """Drop JAX's compiled executables after a test that leaves the process near a limit.

    Each XLA CPU executable keeps a few anonymous memory mappings for its JIT-compiled code, and
    the suite compiles thousands of programs. Kept for the whole session they reach Linux's
    per-process limit (``vm.max_map_count``, 65530 by default), where the next compilation crashes
    the interpreter (SIGSEGV/SIGABRT inside ``backend_compile``; one module alone, torch_bridge's
    op tests, did). Dropping them only when needed, rather than after every module, keeps the
    programs that later modules share (the op case table's).
    """
    yield
    maps, resident = _recent_memory_map_count(), _resident_bytes()
    over_maps = maps > max(_MAP_BUDGET, _AFTER_LAST_CLEAR["maps"] + _REGROWTH["maps"])
    over_resident = resident > max(_RESIDENT_BUDGET, _AFTER_LAST_CLEAR["resident"] + _REGROWTH["resident"])
    if over_maps or over_resident:
        jax.clear_caches()
        gc.collect()
        _LAST_MAP_READING.update(maps=_memory_map_count(), programs=_COMPILES["programs"])
        _AFTER_LAST_CLEAR.update(maps=_LAST_MAP_READING["maps"], resident=_resident_bytes())
        _COMPILES["cache_clears"] += 1
        _PER_TEST["cache_clears"] += 1


# ---------------------------------------------------------------------------------------------
# The suite's cost in XLA compilations, printed after the test summary (issue "Minutes, not
# hours": most of the suite's time is compiling, so this is the figure to keep down).
# ---------------------------------------------------------------------------------------------

_COMPILES = {"programs": 0, "seconds": 0.0, "cache_hits": 0, "trace_seconds": 0.0, "lower_seconds": 0.0, "cache_clears": 0}
_DURATION_KEYS = {
    "/jax/core/compile/jaxpr_trace_duration": "trace_seconds",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower_seconds",
    "/jax/core/compile/backend_compile_duration": "seconds",
}
# GEOMJAX_TEST_PROFILE=<file>: each worker appends one JSON line per test (its compile figures),
# to find where the suite's compile time goes (``tools/profile_tests.py`` sums them per file).
_PROFILE_PATH = os.environ.get("GEOMJAX_TEST_PROFILE")
_PER_TEST = dict.fromkeys(_COMPILES, 0.0)


# With the profile on, each backend compile is also charged to the line that caused it: the first
# frame of this repository outside the virtual environment (an eager ``jnp`` call compiles a
# one-primitive program there). ``tools/profile_tests.py --by site`` sums them.
_PER_TEST_SITES: dict[str, list[float]] = {}
_REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__))) + os.sep


def _compile_site() -> str:
    import traceback

    for frame in reversed(traceback.extract_stack()[:-2]):
        if frame.filename.startswith(_REPO) and f"{os.sep}.venv{os.sep}" not in frame.filename and not frame.filename.endswith("conftest.py"):
            return f"{frame.filename[len(_REPO):]}:{frame.lineno}"
    return "?"


def _count_compile(event: str, duration: float, **_) -> None:
    key = _DURATION_KEYS.get(event)
    if key is None:
        return
    _COMPILES[key] += duration
    _PER_TEST[key] += duration
    if key == "seconds":
        _COMPILES["programs"] += 1
        _PER_TEST["programs"] += 1
        if _PROFILE_PATH:
            count_and_seconds = _PER_TEST_SITES.setdefault(_compile_site(), [0, 0.0])
            count_and_seconds[0] += 1
            count_and_seconds[1] += duration


def _count_cache_hit(event: str, **_) -> None:
    if event == "/jax/compilation_cache/cache_hits":
        _COMPILES["cache_hits"] += 1
        _PER_TEST["cache_hits"] += 1


jax.monitoring.register_event_duration_secs_listener(_count_compile)
jax.monitoring.register_event_listener(_count_cache_hit)


if _PROFILE_PATH:
    import json
    import time

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_protocol(item, nextitem):
        _PER_TEST.update(dict.fromkeys(_PER_TEST, 0.0))
        _PER_TEST_SITES.clear()
        start = time.perf_counter()
        yield
        record = {"test": item.nodeid, "wall": time.perf_counter() - start, **_PER_TEST, "sites": dict(_PER_TEST_SITES)}
        with open(_PROFILE_PATH, "a") as profile:
            profile.write(json.dumps(record) + "\n")


def pytest_sessionfinish(session):
    workeroutput = getattr(session.config, "workeroutput", None)
    if workeroutput is not None:  # an xdist worker: report to the controller
        workeroutput["xla_compiles"] = dict(_COMPILES)


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node, error):
    for key, value in getattr(node, "workeroutput", {}).get("xla_compiles", {}).items():
        _COMPILES[key] += value


def pytest_terminal_summary(terminalreporter):
    terminalreporter.write_line(
        f"XLA compilations: {_COMPILES['programs']:.0f} programs, {_COMPILES['seconds']:.0f} s of compile time "
        f"(persistent-cache hits among them: {_COMPILES['cache_hits']:.0f}); "
        f"{_COMPILES['trace_seconds']:.0f} s tracing, {_COMPILES['lower_seconds']:.0f} s lowering; "
        f"caches cleared {_COMPILES['cache_clears']:.0f} times near a memory limit"
    )

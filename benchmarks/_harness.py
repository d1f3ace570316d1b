"""Shared timing, memory and reporting helpers for the benchmark scripts.

Every benchmark times geomjax and its baselines in one process and prints ratios; absolute times
are only quoted for GPU runs. Results are also written to ``benchmarks/results/<name>.json`` so the
README tables can be regenerated from them (``python benchmarks/report.py``).
"""

from __future__ import annotations

import json
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import jax

RESULTS = Path(__file__).parent / "results"
# A --quick run (smaller sizes, same code paths) saves ``<name>_quick.json``, never over the
# full-size results that the README tables show.
QUICK = "--quick" in sys.argv[1:]


def block(x):
    """Wait for JAX (and torch) results so timings include the work."""
    return jax.block_until_ready(x)


def best_time(fn, *, repeat: int = 3, warmup: int = 1) -> float:
    """Best wall time of ``fn()`` over ``repeat`` runs after ``warmup`` runs (seconds)."""
    for _ in range(warmup):
        block(fn())
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        block(fn())
        times.append(time.perf_counter() - start)
    return min(times)


def best_times_interleaved(fns: dict, *, repeat: int = 3) -> dict:
    """Best wall time (seconds) of each ``fns[name]()`` over ``repeat`` rounds, each round running
    every function once in turn: a slow spell of a shared machine then hits all of them alike,
    and the ratios between them hold better than with one function's runs after another's."""
    times: dict = {name: [] for name in fns}
    for _ in range(repeat):
        for name, fn in fns.items():
            start = time.perf_counter()
            block(fn())
            times[name].append(time.perf_counter() - start)
    return {name: min(values) for name, values in times.items()}


def peak_rss_bytes_of(code: str) -> int:
    """Run ``code`` in a fresh Python process and return its peak resident memory in bytes.

    A subprocess keeps earlier allocations of the benchmark itself out of the figure. The peak is
    read from ``VmHWM`` in ``/proc/self/status``: ``ru_maxrss`` would report the parent's peak,
    which a forked child inherits.
    """
    script = f"{code}\n{_PRINT_PEAK}"
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True).stdout
    kb = int(next(line.split()[1] for line in out.splitlines() if line.startswith("PEAK_RSS_KB")))
    return kb * 1024


_PRINT_PEAK = "print('PEAK_RSS_KB', next(l.split()[1] for l in open('/proc/self/status') if l.startswith('VmHWM:')))"


def self_peak_rss_bytes() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def machine() -> dict:
    devices = jax.devices()
    return {
        "platform": devices[0].platform,
        "device": getattr(devices[0], "device_kind", str(devices[0])),
        "cpu": platform.processor() or platform.machine(),
        "python": platform.python_version(),
        "jax": jax.__version__,
    }


def report(name: str, rows: list[dict]) -> None:
    """Print ``rows`` as a table and save them with the machine description.

    Each row is a dict such as ``{"case": ..., "ours_s": ..., "baseline_s": ..., "ratio": ...,
    "target": ..., "met": ...}``; keys are free-form but should be consistent within a script.
    """
    keys = list(dict.fromkeys(k for row in rows for k in row))
    widths = {k: max(len(k), *(len(_fmt(row.get(k))) for row in rows)) for k in keys}
    print("  ".join(k.ljust(widths[k]) for k in keys))
    for row in rows:
        print("  ".join(_fmt(row.get(k)).ljust(widths[k]) for k in keys))
    if QUICK and not name.endswith("_quick"):
        name = f"{name}_quick"
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{name}.json").write_text(json.dumps({"machine": machine(), "rows": rows}, indent=2))


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return "" if v is None else str(v)

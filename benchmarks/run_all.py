"""Run every benchmark, then regenerate the README's performance tables; print the times.

Usage: ``python benchmarks/run_all.py [--quick] [--only morph,rbf]``

Each ``benchmarks/bench_*.py`` runs in its own process, one after the other (timings on a small
machine are only meaningful without another job beside them). A full run rewrites the README's
tables from ``benchmarks/results/*.json`` (``report.py --write-readme``); ``--quick`` runs every
script at its smaller size (same code paths, under a minute each on a 2-core CPU), saves
``*_quick.json`` and prints those tables without touching the README. A failing script is
reported and the others still run; the exit status is 1 if any failed.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).parent


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="every script with --quick")
    parser.add_argument("--only", default="", help="comma-separated script names without bench_ (e.g. morph,rbf)")
    args = parser.parse_args()
    scripts = sorted(HERE.glob("bench_*.py"))
    if args.only:
        wanted = {name.strip() for name in args.only.split(",")}
        unknown = wanted - {s.stem.removeprefix("bench_") for s in scripts}
        if unknown:
            parser.error(f"no such benchmark: {', '.join(sorted(unknown))}")
        scripts = [s for s in scripts if s.stem.removeprefix("bench_") in wanted]
    times, failed = {}, []
    start = time.perf_counter()
    for script in scripts:
        print(f"== {script.name}{' --quick' if args.quick else ''}", flush=True)
        begin = time.perf_counter()
        run = subprocess.run([sys.executable, str(script), *(["--quick"] if args.quick else [])], check=False)
        times[script.name] = time.perf_counter() - begin
        if run.returncode != 0:
            failed.append(script.name)
    report = [sys.executable, str(HERE / "report.py"), "--quick" if args.quick else "--write-readme"]
    subprocess.run(report, check=True, stdout=subprocess.DEVNULL if not args.quick else None)
    print("\n== times")
    for name, seconds in times.items():
        print(f"   {name:32s} {seconds:7.1f} s{'  FAILED' if name in failed else ''}")
    print(f"   {'total':32s} {time.perf_counter() - start:7.1f} s")
    if not args.quick:
        print("README.md performance tables regenerated from benchmarks/results/*.json")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())

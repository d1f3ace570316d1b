"""Render the saved benchmark results as Markdown tables, optionally into README.md.

Usage: python benchmarks/report.py [--write-readme | --quick]

Each ``benchmarks/bench_*.py`` saves ``benchmarks/results/<name>.json`` (machine description and
rows). This script prints one table per result file and, with ``--write-readme``, replaces the
block between ``<!-- perf-table:start -->`` and ``<!-- perf-table:end -->`` in README.md.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

HERE = Path(__file__).parent
README = HERE.parent / "README.md"
START, END = "<!-- perf-table:start -->", "<!-- perf-table:end -->"


def _cell(value) -> str:
    if isinstance(value, bool):
        return "yes" if value else "**no**"
    if isinstance(value, float):
        return f"{value:.3g}"
    return "" if value is None else str(value)


def _script_for(result_name: str) -> str:
    """The bench script that wrote a result file (``torch_bridge_large`` -> ``bench_torch_bridge.py``)."""
    scripts = sorted((p.stem for p in HERE.glob("bench_*.py")), key=len, reverse=True)
    return next((f"{s}.py" for s in scripts if result_name.startswith(s.removeprefix("bench_"))), "?")


def render(quick: bool = False) -> str:
    """Markdown tables of the full-size results (``quick``: of the ``--quick`` runs instead)."""
    parts = []
    for path in sorted((HERE / "results").glob("*.json")):
        if path.stem.endswith("_quick") != quick:
            continue
        data = json.loads(path.read_text())
        rows, machine = data["rows"], data["machine"]
        keys = list(dict.fromkeys(k for row in rows for k in row))
        where = f"{machine['platform']} ({machine['device']}), jax {machine['jax']}"
        parts.append(f"**{path.stem}** — measured on {where}, by `benchmarks/{_script_for(path.stem)}`\n")
        parts.append("| " + " | ".join(keys) + " |")
        parts.append("|" + "---|" * len(keys))
        parts.extend("| " + " | ".join(_cell(row.get(k)) for k in keys) + " |" for row in rows)
        parts.append("")
    return "\n".join(parts)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--write-readme", action="store_true")
    parser.add_argument("--quick", action="store_true", help="the tables of the --quick runs (never written to README.md)")
    args = parser.parse_args()
    if args.quick and args.write_readme:
        parser.error("the README shows full-size results: --quick and --write-readme exclude each other")
    tables = render(quick=args.quick)
    print(tables)
    if args.write_readme:
        text = README.read_text()
        head, rest = text.split(START, 1)
        _, tail = rest.split(END, 1)
        README.write_text(f"{head}{START}\n{tables}\n{END}{tail}")


if __name__ == "__main__":
    main()

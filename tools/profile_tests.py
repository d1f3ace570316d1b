"""Sum the per-test compile profile that ``GEOMJAX_TEST_PROFILE=<file> pytest ...`` writes.

Usage: ``python tools/profile_tests.py <file> [--by file|function|test|site] [--top N]``. Prints, per
group, wall seconds, backend-compile seconds, tracing and lowering seconds, programs compiled and
persistent-cache hits, largest wall time first. ``--by site`` instead counts the programs compiled
from each source line of the repository (its first frame outside the virtual environment) and
their backend-compile seconds, most programs first: eager ``jnp`` calls in library or test code
each compile a one-primitive program per shape.
"""

import argparse
import collections
import json

FIELDS = ("wall", "seconds", "trace_seconds", "lower_seconds", "programs", "cache_hits")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("profile")
    parser.add_argument("--by", choices=("file", "function", "test", "site"), default="file")
    parser.add_argument("--top", type=int, default=30)
    args = parser.parse_args()
    if args.by == "site":
        print_sites(args.profile, args.top)
        return
    totals = collections.defaultdict(lambda: dict.fromkeys(FIELDS, 0.0))
    with open(args.profile) as lines:
        for line in lines:
            record = json.loads(line)
            key = record["test"]
            if args.by == "file":
                key = key.split("::")[0]
            elif args.by == "function":
                key = key.split("[")[0]
            for field in FIELDS:
                totals[key][field] += record[field]
    grand = {field: sum(t[field] for t in totals.values()) for field in FIELDS}
    print(f"{'wall':>7} {'compile':>7} {'trace':>6} {'lower':>6} {'progs':>6} {'hits':>5}  group")
    for key, t in [("TOTAL", grand), *sorted(totals.items(), key=lambda kv: -kv[1]["wall"])[: args.top]]:
        print(
            f"{t['wall']:7.1f} {t['seconds']:7.1f} {t['trace_seconds']:6.1f} {t['lower_seconds']:6.1f} "
            f"{t['programs']:6.0f} {t['cache_hits']:5.0f}  {key}"
        )


def print_sites(profile: str, top: int) -> None:
    sites = collections.defaultdict(lambda: [0, 0.0])
    with open(profile) as lines:
        for line in lines:
            for site, (count, seconds) in json.loads(line).get("sites", {}).items():
                sites[site][0] += count
                sites[site][1] += seconds
    total = [sum(v[0] for v in sites.values()), sum(v[1] for v in sites.values())]
    print(f"{'progs':>6} {'compile':>7}  site")
    for site, (count, seconds) in [("TOTAL", total), *sorted(sites.items(), key=lambda kv: -kv[1][0])[:top]]:
        print(f"{count:6.0f} {seconds:7.1f}  {site}")


if __name__ == "__main__":
    main()

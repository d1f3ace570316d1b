"""Sum the per-test compile profile that ``GEOMJAX_TEST_PROFILE=<file> pytest ...`` writes.

Usage: ``python tools/profile_tests.py <file> [--by file|function|test] [--top N]``. Prints, per
group, wall seconds, backend-compile seconds, tracing and lowering seconds, programs compiled and
persistent-cache hits, largest wall time first.
"""

import argparse
import collections
import json

FIELDS = ("wall", "seconds", "trace_seconds", "lower_seconds", "programs", "cache_hits")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("profile")
    parser.add_argument("--by", choices=("file", "function", "test"), default="file")
    parser.add_argument("--top", type=int, default=30)
    args = parser.parse_args()
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


if __name__ == "__main__":
    main()

"""The quick tier covers every registered op: value, gradient, torch_bridge call, bad input."""

import subprocess
import sys

import pytest

from geomjax._registry import REGISTRY

from .quick_tier import quick_tests, required_kinds

pytestmark = pytest.mark.quick


def _collected_quick_tier(request) -> set[tuple[str, str]]:
    """``(op, kind)`` of the collected tests that carry the quick marker with an op (tests/conftest.py
    adds them from tests/quick_tier.py by node id, so a renamed or removed test leaves its op
    uncovered). A session that did not collect every named test (this file run alone, a few
    files) collects the tier in a subprocess instead."""
    items = request.session.items
    if not set(quick_tests()) <= {item.nodeid for item in items}:
        collected = subprocess.run(
            [sys.executable, "-m", "pytest", "--collect-only", "-q", "-m", "quick", "-p", "no:cacheprovider"],
            cwd=request.config.rootpath, capture_output=True, text=True, timeout=300, check=True,
        )  # fmt: skip
        nodes = {line for line in collected.stdout.splitlines() if "::" in line}
        table = quick_tests()
        return {pair for node in nodes for pair in table.get(node, ())}
    return {(mark.kwargs["op"], mark.kwargs["kind"]) for item in items for mark in item.iter_markers("quick") if "op" in mark.kwargs}


def test_every_registered_op_is_in_the_quick_tier(request):
    covered = _collected_quick_tier(request)
    missing = [(op, kind) for op in REGISTRY for kind in required_kinds(op) if (op, kind) not in covered]
    assert not missing, f"registered ops without quick-tier tests (add them to tests/quick_tier.py): {missing}"

"""The quick tier covers every registered op: value, gradient, torch_bridge call, bad input."""

import pytest

from geomjax._registry import REGISTRY

from .quick_tier import required_kinds

pytestmark = pytest.mark.quick


def test_every_registered_op_is_in_the_quick_tier(request):
    # The collected tests that carry the quick marker with an op (tests/conftest.py adds them from
    # tests/quick_tier.py by node id, so a renamed or removed test leaves its op uncovered here).
    covered = {
        (mark.kwargs["op"], mark.kwargs["kind"])
        for item in request.session.items
        for mark in item.iter_markers("quick")
        if "op" in mark.kwargs
    }
    missing = [(op, kind) for op in REGISTRY for kind in required_kinds(op) if (op, kind) not in covered]
    assert not missing, f"registered ops without quick-tier tests (add them to tests/quick_tier.py): {missing}"

"""The allocator thresholds a diagnosis runs under: a call's result unchanged, nested and failing calls unwound."""

import numpy as np
import pytest

from detector import allocator


def test_reuse_freed_memory_returns_the_result_and_unwinds():
    @allocator.reuse_freed_memory
    def inner(n):
        return float(np.ones((n, n)).sum())

    @allocator.reuse_freed_memory
    def outer(n):
        assert allocator._DEPTH[0] == (0 if allocator._glibc() is None else 1)
        return inner(n) + inner(2 * n)

    assert outer(512) == 512 * 512 * 5
    assert allocator._DEPTH[0] == 0


def test_reuse_freed_memory_unwinds_on_error():
    @allocator.reuse_freed_memory
    def fails():
        raise ValueError("no")

    with pytest.raises(ValueError):
        fails()
    assert allocator._DEPTH[0] == 0

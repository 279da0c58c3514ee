"""Shared fixtures."""

import pytest

from sparsecomm.sharding import fast_compile as set_fast_compile


@pytest.fixture
def fast_compile():
    """Compile with most XLA optimisations off (the switch ``reproduce --quick`` uses): for
    end-to-end tests with tiny budgets, whose time goes to compiling, not to running."""
    previous = set_fast_compile(True)
    yield
    set_fast_compile(previous)

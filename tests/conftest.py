"""Shared fixtures."""

import pytest

from sparsecomm.reproduce import _fast_compile


@pytest.fixture
def fast_compile():
    """Compile with most XLA optimisations off (the switch ``reproduce --quick`` uses): for
    end-to-end tests with tiny budgets, whose time goes to compiling, not to running."""
    previous = _fast_compile(True)
    yield
    _fast_compile(previous)

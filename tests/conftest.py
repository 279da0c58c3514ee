"""Shared fixtures."""

import jax
import pytest


@pytest.fixture
def fast_compile():
    """Compile with most XLA optimisations off: for end-to-end tests with tiny budgets, whose
    time goes to compiling several programs, not to running them."""
    previous = bool(jax.config._read("jax_disable_most_optimizations"))
    jax.config.update("jax_disable_most_optimizations", True)
    yield
    jax.config.update("jax_disable_most_optimizations", previous)

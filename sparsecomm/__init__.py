"""sparsecomm: sparse discrete communication learning for multi-agent cooperation (JAX)."""

__version__ = "0.1.0"

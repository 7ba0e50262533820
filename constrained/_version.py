"""The package version (one place; pyproject.toml has the same, tests/test_startup.py checks)."""

__version__ = "0.1.0"

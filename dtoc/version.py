"""The package version, written once (pyproject.toml reads the same string)."""

__version__ = "0.1.0"

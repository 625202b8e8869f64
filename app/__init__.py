"""Locus: a server-side, real-time indoor location engine for many tags."""

from importlib.metadata import version

__version__ = version("locus")
"""The installed package's version: pyproject.toml is its one source."""

"""The version of aefabmap, written once (the package metadata reads it, pyproject.toml)."""

__version__ = "0.2.0"

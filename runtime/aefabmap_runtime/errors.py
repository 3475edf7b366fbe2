"""The one exception hierarchy of aefabmap.

The library raises these; only the CLI turns them into a message and an exit code.
"""

from __future__ import annotations


class AefabmapError(Exception):
    """Base class of every error aefabmap raises on purpose."""

    exit_code = 1


class ConfigError(AefabmapError):
    """A configuration value or command-line option is invalid."""

    exit_code = 2


class BundleError(AefabmapError):
    """A model bundle is missing, corrupt, of the wrong version or inconsistent."""

    exit_code = 3


class StateError(AefabmapError):
    """A saved map state (``--state DIR``) is corrupt, truncated, of another bundle or settings,
    of a newer format, or cannot be written."""

    exit_code = 3


class InputError(AefabmapError):
    """An input (image, frame payload, observation, data file) is malformed."""

    exit_code = 4


class ImageDecodeError(InputError):
    """An image payload could not be decoded into pixels."""


class DataNotFoundError(InputError):
    """A data directory or file that was asked for does not exist or is empty."""


class TransportError(AefabmapError):
    """A Zenoh session, publisher or subscriber failed."""

    exit_code = 5


class LogError(AefabmapError):
    """An MCAP log could not be written or read."""

    exit_code = 6

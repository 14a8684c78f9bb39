"""Exception types of the NMPC core (no ROS imports here)."""

from __future__ import annotations


class NmpcError(Exception):
    """Base class of every error raised by nmpc_avoid_ros."""


class ConfigError(NmpcError, ValueError):
    """A setting or configuration file is invalid; the message names the setting."""


class RegionError(NmpcError, ValueError):
    """An avoidance region is malformed (bad shape, NaN, wrong frame, too many)."""


class ExpressionError(NmpcError, ValueError):
    """An algebraic region expression is malformed or uses something not allowed."""


class InputError(NmpcError, ValueError):
    """A measured state, target or command vector is invalid (size, NaN, inf)."""

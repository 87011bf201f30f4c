"""Exceptions raised by colmap-pvs. Every message names the offending value."""

from __future__ import annotations


class ColmapPVSError(Exception):
    """Base class for all errors raised by colmap-pvs."""


class ConfigError(ColmapPVSError, ValueError):
    """An unknown config key, or a value of the wrong type or range."""


class WorkspaceError(ColmapPVSError):
    """A missing or malformed COLMAP (dense) workspace or sparse model."""


class UnsupportedCameraError(WorkspaceError):
    """A camera model that is not a pinhole; it must be undistorted first."""


class MapFormatError(ColmapPVSError):
    """A corrupt, truncated or otherwise unreadable COLMAP ``.bin`` array file."""


class CheckpointError(ColmapPVSError):
    """A missing, corrupt or mismatched model checkpoint."""


class ShapeError(ColmapPVSError, ValueError):
    """A tensor or array whose shape does not match the documented one."""


class DistributedError(ColmapPVSError):
    """A scale-out (Ray) failure: Ray missing, no workers, or a reference whose workers kept dying."""


class OutputError(ColmapPVSError, OSError):
    """An output that cannot be written: read-only folder, full disk, ... (nothing half-written is left)."""


class MemoryBudgetError(ColmapPVSError, MemoryError):
    """A forward pass whose estimated peak memory exceeds the budget; the message names a size that fits."""

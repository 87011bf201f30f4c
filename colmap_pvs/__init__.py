"""colmap-pvs: CPU-first learned dense multi-view stereo (PVSNet) for COLMAP workspaces."""

from __future__ import annotations

import logging

__version__ = "0.2.0.dev0"

logging.getLogger(__name__).addHandler(logging.NullHandler())

"""COLMAP's own dense tools through pycolmap: ``stereo_fusion`` and ``poisson_mesher``.

:mod:`colmap_pvs.fusion` (``--method colmap``) and :mod:`colmap_pvs.mesh` (``--method colmap``) call
these; the options are plain dictionaries / numbers there.
"""

from __future__ import annotations

import os
from typing import Any

import pycolmap

__all__ = [
    "poisson_meshing",
    "stereo_fusion",
    "stereo_fusion_option_types",
    "stereo_fusion_options_ok",
]

_METHODS = {"check", "mergedict", "summary", "todict"}


def stereo_fusion_option_types() -> dict[str, type]:
    """The keys of ``pycolmap.StereoFusionOptions`` and the type of each default value."""
    defaults = pycolmap.StereoFusionOptions().todict()
    return {k: type(v) for k, v in defaults.items() if k not in _METHODS}


def _fusion_options(values: dict[str, Any]) -> pycolmap.StereoFusionOptions:
    options = pycolmap.StereoFusionOptions()
    for key, value in values.items():
        setattr(options, key, value)
    return options


def stereo_fusion_options_ok(values: dict[str, Any]) -> bool:
    """Whether COLMAP's own ``check()`` accepts the fusion options ``values`` (others at defaults)."""
    return bool(_fusion_options(values).check())


def stereo_fusion(
    output_path: str | os.PathLike,
    workspace_path: str | os.PathLike,
    *,
    input_type: str,
    options: dict[str, Any],
) -> None:
    """COLMAP's ``stereo_fusion`` of the dense workspace ``workspace_path`` into the PLY ``output_path``
    (and its ``.vis``); ``options`` are ``StereoFusionOptions`` values (others at COLMAP's defaults).

    Raises:
        RuntimeError: COLMAP failed (its message).
    """
    pycolmap.stereo_fusion(
        str(output_path),
        str(workspace_path),
        input_type=input_type,
        options=_fusion_options(options),
        output_type="PLY",
    )


def poisson_meshing(
    input_path: str | os.PathLike,
    output_path: str | os.PathLike,
    *,
    depth: int,
    trim: float,
    point_weight: float,
    num_threads: int = -1,
) -> None:
    """COLMAP's screened Poisson mesher (``colmap poisson_mesher``) of the cloud ``input_path``."""
    options = pycolmap.PoissonMeshingOptions()
    options.depth = depth
    options.trim = trim
    options.point_weight = point_weight
    options.num_threads = num_threads
    pycolmap.poisson_meshing(str(input_path), str(output_path), options=options)

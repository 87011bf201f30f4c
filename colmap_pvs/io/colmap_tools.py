"""COLMAP's own dense tools through pycolmap: ``stereo_fusion`` and ``poisson_mesher``.

:mod:`colmap_pvs.fusion` (``--method colmap``) and :mod:`colmap_pvs.mesh` (``--method colmap``) call
these; the options are plain dictionaries / numbers there. ``fuse --colmap_options key=value`` strings
are checked by :func:`parse_colmap_options` against COLMAP's own option types.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np
import pycolmap

from ..config import parse_bool
from ..errors import ConfigError

__all__ = [
    "COLMAP_DEFAULTS",
    "parse_colmap_options",
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


#: Our defaults for ``method="colmap"`` (every other option keeps COLMAP's value): learned maps are
#: dense but noisier per pixel than patch-match's, and their normals noisier, so COLMAP's own
#: ``min_num_pixels=5`` / ``max_normal_error=10`` discard most of the surface (``benchmarks/RESULTS.md``,
#: "pycolmap's fusion options for learned maps").
COLMAP_DEFAULTS: dict[str, Any] = {"min_num_pixels": 3, "max_normal_error": 20.0}


def parse_colmap_options(items: tuple[str, ...] | list[str]) -> dict[str, Any]:
    """Parse ``key=value`` strings into typed ``pycolmap.StereoFusionOptions`` values.

    ``bounding_box`` takes six numbers ``xmin,ymin,zmin,xmax,ymax,zmax`` (``,`` or space separated).

    Raises:
        ConfigError: a malformed item, an unknown key (named, with the known ones) or a value of the
            wrong type; also when the resulting options fail COLMAP's own ``check()``.
    """
    types_ = stereo_fusion_option_types()
    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = str(item).partition("=")
        key, value = key.strip(), value.strip()
        if not sep or not key:
            raise ConfigError(f"colmap_options: expected key=value, got {item!r}")
        if key not in types_:
            raise ConfigError(
                f"colmap_options: unknown StereoFusionOptions key {key!r}; known keys are {sorted(types_)}"
            )
        tp = types_[key]
        try:
            if tp is bool:
                parsed: Any = parse_bool(value)
            elif tp is int:
                parsed = int(value)
            elif tp is float:
                parsed = float(value)
            elif key == "bounding_box":
                nums = [float(v) for v in value.replace(",", " ").split()]
                if len(nums) != 6:
                    raise ValueError("expected 6 numbers")
                parsed = (np.array(nums[:3], dtype=np.float32), np.array(nums[3:], dtype=np.float32))
            else:
                parsed = value
        except (ValueError, ConfigError) as exc:
            raise ConfigError(
                f"colmap_options: bad value {value!r} for {key!r} (expected {tp.__name__}): {exc}"
            ) from None
        out[key] = parsed
    if not stereo_fusion_options_ok({**COLMAP_DEFAULTS, **out}):
        raise ConfigError(f"colmap_options: COLMAP rejects the fusion options {list(items)} (see its log)")
    return out

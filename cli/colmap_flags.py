"""COLMAP's ``patch_match_stereo`` flags on ``colmap-pvs stereo`` (alias ``patch_match_stereo``).

A script that runs ``colmap patch_match_stereo --workspace_path dense --workspace_format COLMAP
--PatchMatchStereo.geom_consistency true`` keeps working after swapping the binary for
``colmap-pvs``. Flags with a meaning here are translated to :class:`colmap_pvs.stereo.StereoConfig`
fields (the fixed depth range, the geometric filter's thresholds, ...); flags of COLMAP's patch-match
optimiser (window, NCC, sampling, ...) have no meaning for a learned network and are named in one
warning, never dropped silently.
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import Callable
from typing import Any

from colmap_pvs.config import check_threads, parse_bool
from colmap_pvs.errors import ConfigError

logger = logging.getLogger("colmap_pvs.cli")

_DEST = "_colmap:"


def _int(flag: str, text: str) -> int:
    try:
        return int(str(text).strip())
    except ValueError:
        raise ConfigError(f"--{flag}: expected an integer, got {text!r}") from None


def _float(flag: str, text: str) -> float:
    try:
        return float(str(text).strip())
    except ValueError:
        raise ConfigError(f"--{flag}: expected a number, got {text!r}") from None


def _bool(flag: str, text: str) -> bool:
    try:
        return parse_bool(text)
    except ConfigError:
        raise ConfigError(f"--{flag}: expected a boolean (true/false/1/0), got {text!r}") from None


def _max_image_size(flag: str, text: str) -> dict[str, Any]:
    """= --max_image_size (COLMAP's -1, full size, is our <= 0)"""
    return {"max_image_size": _int(flag, text)}  # COLMAP's -1 (full size) is our <= 0


def _geom_consistency(flag: str, text: str) -> dict[str, Any]:
    """= --geom_consistency"""
    return {"geom_consistency": _bool(flag, text)}


def _min_num_consistent(flag: str, text: str) -> dict[str, Any]:
    """= --geom_min_consistent"""
    return {"geom_min_consistent": _int(flag, text)}


def _min_triangulation_angle(flag: str, text: str) -> dict[str, Any]:
    """= --geom_min_triangulation_angle"""
    return {"geom_min_triangulation_angle": _float(flag, text)}


def _geom_max_cost(flag: str, text: str) -> dict[str, Any]:
    """= --geom_max_reproj_error (the forward-backward reprojection error in px)"""
    return {"geom_max_reproj_error": _float(flag, text)}


def _depth_bound(flag: str, text: str) -> dict[str, Any]:
    """with the other bound, = --depth_range MIN MAX (COLMAP's -1, from the sparse points, is our default)"""
    return {}  # the pair is translated together, by translate_colmap_flags


def _depth_range(given: dict[str, str]) -> dict[str, Any]:
    """``--depth_range`` from COLMAP's ``depth_min``/``depth_max``: COLMAP uses a fixed range only when
    both are >= 0; a negative one (its default, -1) keeps the ranges from the sparse points."""
    names = [f"PatchMatchStereo.depth_{k}" for k in ("min", "max")]
    bounds = {n: _float(n, given[n]) for n in names if n in given}
    if not bounds or any(v < 0 for v in bounds.values()):
        return {}
    if len(bounds) == 1:
        (flag, value), = bounds.items()
        other = next(n for n in names if n != flag)
        raise ConfigError(f"--{flag} {value:g} needs --{other} too: a fixed depth range takes both bounds")
    low, high = bounds[names[0]], bounds[names[1]]
    if not 0 < low < high:  # COLMAP takes a minimum of 0; a depth of 0 is no depth to sweep here
        raise ConfigError(f"--{names[0]} {low:g} --{names[1]} {high:g}: a fixed depth range needs "
                          "0 < depth_min < depth_max (or -1 for each image's range from its sparse points)")
    return {"depth_range": (low, high)}


def _num_threads(flag: str, text: str) -> dict[str, Any]:
    """= --threads (COLMAP's -1, all cores, is our 0)"""
    n = _int(flag, text)
    if n != -1:
        check_threads(f"--{flag}", n, auto=-1)  # named as the user typed it, with COLMAP's -1
    return {"threads": max(n, 0)}  # COLMAP's -1 (all cores) is torch's default, our 0


def _gpu_index(flag: str, text: str) -> dict[str, Any]:
    """= --device: -1 is auto, a GPU index is cuda (the first visible GPU)"""
    items = [s.strip() for s in str(text).split(",") if s.strip()]
    indices = [_int(flag, s) for s in items]
    if not indices or indices == [-1]:
        return {"device": "auto"}
    if any(i < 0 for i in indices):
        raise ConfigError(f"--{flag}: expected -1 or GPU indices, got {text!r}")
    if indices != [0]:
        logger.warning(
            "--%s %s: colmap-pvs runs on one GPU, the first visible one; select it with "
            "CUDA_VISIBLE_DEVICES=%d", flag, text, indices[0],
        )
    return {"device": "cuda"}


def _workspace_format(flag: str, text: str) -> dict[str, Any]:
    """COLMAP (the only format; PMVS is refused)"""
    if str(text).strip().upper() != "COLMAP":
        raise ConfigError(f"--{flag} {text}: only the COLMAP workspace format is supported (not PMVS)")
    return {}


def _config_path(flag: str, text: str) -> dict[str, Any]:
    """refused when set: patch-match.cfg is read from WORKSPACE/stereo/"""
    if str(text).strip():
        raise ConfigError(
            f"--{flag} {text!r}: colmap-pvs reads WORKSPACE/stereo/patch-match.cfg; copy the file there"
        )
    return {}


def _project_path(flag: str, text: str) -> dict[str, Any]:
    """refused: .ini project files are not read"""
    raise ConfigError(f"--{flag} {text!r}: .ini project files are not read; pass the options as flags")


#: flag -> translation into StereoConfig fields (``None``: accepted, no meaning here).
PATCH_MATCH_STEREO_FLAGS: dict[str, Callable[[str, str], dict[str, Any]] | None] = {
    "workspace_format": _workspace_format,
    "pmvs_option_name": None,
    "config_path": _config_path,
    "project_path": _project_path,
    "random_seed": None,
    "PatchMatchStereo.max_image_size": _max_image_size,
    "PatchMatchStereo.geom_consistency": _geom_consistency,
    "PatchMatchStereo.num_threads": _num_threads,
    "PatchMatchStereo.gpu_index": _gpu_index,
    "PatchMatchStereo.depth_min": _depth_bound,
    "PatchMatchStereo.depth_max": _depth_bound,
    "PatchMatchStereo.filter_min_num_consistent": _min_num_consistent,
    "PatchMatchStereo.filter_min_triangulation_angle": _min_triangulation_angle,
    "PatchMatchStereo.filter_geom_consistency_max_cost": _geom_max_cost,
    # COLMAP's patch-match optimiser and its photometric filter: nothing in a learned network matches
    # them (its own min_triangulation_angle weights sources while sampling; filter, filter_min_ncc and
    # geom_consistency_max_cost act on its NCC costs)
    **{
        f"PatchMatchStereo.{name}": None
        for name in (
            "window_radius", "window_step", "sigma_spatial", "sigma_color",
            "num_samples", "ncc_sigma", "min_triangulation_angle", "incident_angle_sigma",
            "num_iterations", "geom_consistency_regularizer", "geom_consistency_max_cost", "filter",
            "filter_min_ncc", "cache_size", "allow_missing_files", "write_consistency_graph",
        )
    },
}


def add_colmap_flags(parser: argparse.ArgumentParser, listed: bool = True) -> None:
    """Add COLMAP's ``patch_match_stereo`` flags (values are translated by :func:`translate_colmap_flags`);
    ``listed=False`` accepts them without listing them in ``--help``."""
    group = parser.add_argument_group(
        "COLMAP patch_match_stereo flags",
        "accepted so that `colmap patch_match_stereo` command lines work unchanged; flags without a "
        "meaning for a learned network are named in a warning",
    ) if listed else parser
    for flag, translate in PATCH_MATCH_STEREO_FLAGS.items():
        if not listed:
            help_text = argparse.SUPPRESS
        elif translate is None:
            help_text = "accepted, no meaning here (ignored with a warning)"
        else:
            help_text = str(translate.__doc__)
        group.add_argument(f"--{flag}", dest=_DEST + flag, default=argparse.SUPPRESS, metavar="V",
                           help=help_text)


def _same(own: Any, value: Any) -> bool:
    """Whether our flag's value (as parsed: text for a list) equals a translated value."""
    if isinstance(value, tuple):
        try:
            return tuple(float(v) for v in own) == value
        except (TypeError, ValueError):
            return False
    return own == value


def translate_colmap_flags(args: argparse.Namespace) -> dict[str, Any]:
    """StereoConfig values from the COLMAP flags in ``args``; warns naming the ignored ones.

    Raises:
        ConfigError: a bad value, an unsupported format, or a COLMAP flag that contradicts our own
            flag for the same setting.
    """
    given = {k[len(_DEST):]: v for k, v in vars(args).items() if k.startswith(_DEST)}
    translated: list[tuple[str, dict[str, Any]]] = []
    ignored = []
    for flag, text in given.items():
        translate = PATCH_MATCH_STEREO_FLAGS[flag]
        if translate is None:
            ignored.append(f"--{flag}")
        else:
            translated.append((f"{flag} {text}", translate(flag, text)))
    translated.append(("PatchMatchStereo.depth_min/depth_max", _depth_range(given)))
    values: dict[str, Any] = {}
    for given_as, items in translated:
        for key, value in items.items():
            own = getattr(args, key, None)
            if hasattr(args, key) and not _same(own, value):
                raise ConfigError(f"--{given_as} contradicts --{key} {own}; give only one of them")
            values[key] = value
    if ignored:
        logger.warning("ignored COLMAP flag(s) without a meaning for colmap-pvs: %s", ", ".join(ignored))
    return values

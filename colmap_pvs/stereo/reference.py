"""One reference image as the ``stereo`` passes see it: its name, sources, files, maps and record.

Each run makes one :class:`Reference` per image, once (:meth:`StereoContext.reference
<colmap_pvs.stereo.context.StereoContext.reference>`: every path computed once). A pass reads its
inputs through it -- its own and its sources' provenance (:meth:`Reference.provenance`), maps
(``ref.paths[stage]``), seeds, visibility and confirmation record -- computes its maps
(:class:`PassMaps`) and what made them (:class:`PassRecord`), and hands ``ref.with_pass(stage, maps,
record)`` to :func:`~colmap_pvs.stereo.outputs.write_pass`, which writes exactly what it holds: the
maps to ``ref.paths[stage]``, the record as ``stereo/provenance/NAME.STAGE.json``.

A :class:`Reference` carries the maps of one pass at most: a pass reads the previous pass's maps from
disk (another process may have made them, and a run over thousands of images cannot keep every
image's maps in memory until its next pass), so the cached one holds paths only.

The path helpers below are the layout of ``stereo/`` beside the workspace's own depth, normal and
confidence maps (:class:`~colmap_pvs.io.workspace.Workspace`).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from types import MappingProxyType

import numpy as np

from ..io.workspace import Workspace
from .config import Stage

#: The passes that write depth maps of their own (the confirmation adds to the geometric ones).
MAP_STAGES: tuple[Stage, ...] = ("photometric", "geometric", "filled")


def provenance_path(ws: Workspace, name: str, stage: Stage) -> Path:
    """``stereo/provenance/NAME.STAGE.json``: what produced that pass's maps of ``name``."""
    ws.depth_map_path(name, stage)  # validates name and stage
    return ws.stereo_dir / "provenance" / f"{name}.{stage}.json"


def visibility_map_path(ws: Workspace, name: str) -> Path:
    """``stereo/visibility_maps/NAME.bin``: the network's learned visibility of each source."""
    ws.depth_map_path(name, "photometric")  # validates name
    return ws.stereo_dir / "visibility_maps" / f"{name}.bin"


def seed_map_path(ws: Workspace, name: str) -> Path:
    """``stereo/seed_maps/NAME.bin``: the depth of the pixels of ``name`` that seed its dense completion
    (at least ``geom_seed_min_consistent`` sources agree within ``geom_seed_depth_error``), 0 elsewhere."""
    ws.depth_map_path(name, "geometric")  # validates name
    return ws.stereo_dir / "seed_maps" / f"{name}.bin"


def seed_provenance_path(ws: Workspace, name: str) -> Path:
    """``stereo/seed_maps/NAME.json``: the fingerprint of the check that made ``NAME.bin``."""
    return seed_map_path(ws, name).with_suffix(".json")


def preview_path(ws: Workspace, name: str, stage: Stage) -> Path:
    """The depth preview of ``name``'s ``stage`` maps: ``stereo/previews/NAME.photometric.depth.png``,
    ``NAME.depth.png`` (geometric) or ``NAME.filled.depth.png``."""
    ws.depth_map_path(name, stage)  # validates name and stage
    infix = "" if stage == "geometric" else f".{stage}"
    return ws.stereo_dir / "previews" / f"{name}{infix}.depth.png"


def confirm_map_path(ws: Workspace, name: str) -> Path:
    """``stereo/confirm_maps/NAME.bin``: the depth of the pixels the confirmation added to ``name``'s
    geometric maps, 0 elsewhere."""
    ws.depth_map_path(name, "geometric")  # validates name
    return ws.stereo_dir / "confirm_maps" / f"{name}.bin"


def confirm_provenance_path(ws: Workspace, name: str) -> Path:
    """``stereo/provenance/NAME.confirm.json``: what the confirmation read, and the fingerprint and
    depth file hash of the geometric maps it wrote."""
    ws.depth_map_path(name, "geometric")  # validates name
    return ws.stereo_dir / "provenance" / f"{name}.confirm.json"


@dataclass(frozen=True)
class PassPaths:
    """The files of one pass's maps of one reference (``stereo/``)."""

    depth: Path  #: ``depth_maps/NAME.STAGE.bin``, written last: it marks the pass done
    normals: Path  #: ``normal_maps/NAME.STAGE.bin``
    confidence: Path  #: ``confidence_maps/NAME.STAGE.bin``
    provenance: Path  #: ``provenance/NAME.STAGE.json`` (:func:`provenance_path`)
    preview: Path  #: the depth preview (:func:`preview_path`); the others share its stem

    @classmethod
    def of(cls, ws: Workspace, name: str, stage: Stage) -> PassPaths:
        return cls(ws.depth_map_path(name, stage), ws.normal_map_path(name, stage),
                   ws.confidence_map_path(name, stage), provenance_path(ws, name, stage),
                   preview_path(ws, name, stage))


@dataclass(frozen=True)
class ReferencePaths:
    """Every file of one reference in ``stereo/``: each pass's maps (``paths[stage]``) and the files
    of one pass only: the photometric pass's ``visibility`` map, the geometric pass's ``seeds`` and
    their ``seed_provenance``, the confirmation's ``confirm_map`` and ``confirm_provenance``."""

    stereo_dir: Path
    passes: Mapping[Stage, PassPaths]
    visibility: Path
    seeds: Path
    seed_provenance: Path
    confirm_map: Path
    confirm_provenance: Path

    @classmethod
    def of(cls, ws: Workspace, name: str) -> ReferencePaths:
        passes = MappingProxyType({stage: PassPaths.of(ws, name, stage) for stage in MAP_STAGES})
        return cls(ws.stereo_dir, passes, visibility_map_path(ws, name), seed_map_path(ws, name),
                   seed_provenance_path(ws, name), confirm_map_path(ws, name),
                   confirm_provenance_path(ws, name))

    def __getitem__(self, stage: Stage) -> PassPaths:
        return self.passes[stage]

    def visibility_preview(self, name: str, k: int, source: str) -> Path:
        """The preview of the learned visibility of the ``k``-th network source ``source``."""
        return self.stereo_dir / "previews" / f"{name}.visibility.{k:02d}.{Path(source).stem}.png"


@dataclass(frozen=True)
class PassMaps:
    """One pass's maps of a reference, float32 at its map size ``[H, W]``.

    Attributes:
        depth: ``[H, W]`` depth along the camera's z axis, 0 where invalid.
        confidence: ``[H, W]`` in ``[0, 1]`` (``docs/CONVENTIONS.md``), 0 where ``depth`` is.
        normals: ``[H, W, 3]`` unit normals in the camera frame, 0 where ``depth`` is; ``None`` for the
            dense completion (which has none).
        visibility: photometric pass only: ``[S, h/4, w/4]`` the network's learned visibility of each of
            its ``S`` sources (``Reference.sources``) at a quarter of the network size; else ``None``.
        seeds: geometric pass only: ``[H, W]`` the dense completion's seeds (0 elsewhere); else ``None``.
    """

    depth: np.ndarray
    confidence: np.ndarray
    normals: np.ndarray | None = None
    visibility: np.ndarray | None = None
    seeds: np.ndarray | None = None


@dataclass(frozen=True)
class PassRecord:
    """What made one pass's maps, as its provenance records it: the ``settings`` whose fingerprint
    decides whether the maps are current, and the ``extra`` facts beside them (image size, sources,
    kept fractions, ...); the geometric pass's ``seed_fingerprint`` marks its seed map current."""

    settings: dict
    extra: dict
    seed_fingerprint: str | None = None


def read_json(path: Path) -> dict | None:
    """A JSON record, or ``None`` when it is missing or unreadable."""
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None


@dataclass(frozen=True)
class Reference:
    """One reference image of a run: ``name``, its network ``sources`` (in the order of the photometric
    visibility maps; set by the photometric pass), its ``depth_range`` (the previews' colour scale;
    ``None`` without a view-selection entry), its files (``paths``, computed once) and, once a pass
    has computed them, that pass's ``stage``, ``maps`` and ``record`` (:meth:`with_pass`)."""

    name: str
    paths: ReferencePaths
    sources: tuple[str, ...] = ()
    depth_range: tuple[float, float] | None = None
    stage: Stage | None = None
    maps: PassMaps | None = None
    record: PassRecord | None = None

    @classmethod
    def of(cls, ws: Workspace, name: str, sources=(), depth_range: tuple[float, float] | None = None,
           ) -> Reference:
        return cls(name, ReferencePaths.of(ws, name), tuple(sources), depth_range)

    def with_pass(self, stage: Stage, maps: PassMaps, record: PassRecord, *,
                  depth_range: tuple[float, float] | None = None, sources=None) -> Reference:
        """This reference with ``stage``'s ``maps`` and ``record`` (and ``depth_range`` and
        ``sources``, when given)."""
        return replace(self, stage=stage, maps=maps, record=record,
                       depth_range=self.depth_range if depth_range is None else depth_range,
                       sources=self.sources if sources is None else tuple(sources))

    def provenance(self, stage: Stage) -> dict | None:
        """The provenance of this reference's ``stage`` maps (``None``: missing or unreadable)."""
        return read_json(self.paths[stage].provenance)

    def has_maps(self, stage: Stage) -> bool:
        """This reference's ``stage`` depth map exists (it is written last: the pass finished)."""
        return self.paths[stage].depth.is_file()

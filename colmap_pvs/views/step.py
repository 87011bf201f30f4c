"""The ``select-views`` step on a workspace: the selection's table and ``stereo/patch-match.cfg``."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

from .config import WIDE_SOURCES_HELP, ViewSelectionConfig
from .selection import ViewSelection, select_views

logger = logging.getLogger(__name__)


def format_selection_table(selection: ViewSelection) -> str:
    """A plain-text table of ``selection`` for the CLI: one row per image, skipped ones included."""
    header = ("reference", "#points", "depth range", "sources (score)")
    rows: list[tuple[str, str, str, str]] = []
    skipped = {s.name: s for s in selection.skipped}
    for name in selection.names:
        ref = selection.references.get(name)
        if ref is not None:
            dmin, dmax = ref.depth_range
            sources = ", ".join(
                f"{s} ({v:.1f})" for s, v in zip(ref.source_names, ref.source_scores, strict=True)
            )
            rows.append((name, str(ref.num_points), f"{dmin:.4g} .. {dmax:.4g}", sources))
        elif name in skipped:
            s = skipped[name]
            rows.append((name, str(s.num_points), "-", f"SKIPPED: {s.reason}"))
    widths = [max(len(r[c]) for r in [header, *rows]) for c in range(3)]

    def line(r: tuple[str, str, str, str]) -> str:
        return f"{r[0]:<{widths[0]}}  {r[1]:>{widths[1]}}  {r[2]:<{widths[2]}}  {r[3]}".rstrip()

    lines = [line(r) for r in rows]
    rule = "-" * max(len(x) for x in [line(header), *lines])
    summary = (
        f"{len(selection.references)} reference(s), {len(selection.skipped)} skipped, "
        f"num_views={selection.config.num_views}"
    )
    return "\n".join([line(header), rule, *lines, rule, summary])


@dataclass(frozen=True)
class SelectViewsConfig:
    """The ``select-views`` step on a dense workspace (writes ``stereo/patch-match.cfg``)."""

    workspace_path: Path = field(metadata={"help": "COLMAP dense workspace (images/, sparse/, stereo/)"})
    num_views: int = field(default=5, metadata={"help": "views per reference: reference + N-1 sources"})
    write_cfg: bool = field(
        default=True, metadata={"help": "write stereo/patch-match.cfg with the explicit source lists"}
    )
    wide_sources: int = field(default=0, metadata={"help": WIDE_SOURCES_HELP})


def run_select_views(config: SelectViewsConfig) -> ViewSelection:
    """Select source views and depth ranges for every image of a workspace.

    Writes ``stereo/patch-match.cfg`` (COLMAP's format: the reference name on one line,
    its comma-separated sources on the next) for the images that were not skipped. A
    ``patch-match.cfg`` that colmap-pvs did not write (``image_undistorter``'s ``__auto__, 20``, or a
    hand-made one) is kept as ``stereo/patch-match.cfg.bak`` first, with a warning.
    """
    from ..io.workspace import load_workspace, write_patch_match_cfg

    ws, model = load_workspace(config.workspace_path)
    selection = select_views(
        model, ViewSelectionConfig(num_views=config.num_views, wide_sources=config.wide_sources)
    )
    if config.write_cfg:
        write_patch_match_cfg(
            ws.patch_match_cfg, {name: ref.source_names for name, ref in selection.references.items()}
        )
        logger.info("wrote %s (%d references)", ws.patch_match_cfg, len(selection.references))
    return selection

"""CLI summaries of the pipeline steps: fuse, mesh, import-poses, reconstruct, demo."""

from __future__ import annotations

import math
from pathlib import Path


def _num(value: float, fmt: str = ".4f") -> str:
    return "n/a" if value is None or not math.isfinite(value) else format(value, fmt)


def report_fuse(result) -> str:
    lines = [
        f"fused cloud: {result.output_path}  ({result.num_points} points from {result.num_images} images, "
        f"method {result.method}, {result.seconds:.1f} s)",
        f"visibility:  {result.vis_path}",
    ]
    lines += [f"  skipped {name}: {why}" for name, why in result.skipped.items()]
    return "\n".join(lines)


def report_mesh(path: Path) -> str:
    from colmap_pvs.io.ply import read_mesh

    vertices, faces = read_mesh(path)
    return f"mesh: {path}  ({len(vertices)} vertices, {len(faces)} faces)"


def report_import_poses(path: Path) -> str:
    import json

    import numpy as np

    from colmap_pvs.io.import_poses import SETTINGS_FILENAME, reprojection_errors
    from colmap_pvs.io.sfm import model_counts

    counts = model_counts(path)
    errs = reprojection_errors(path)
    median = float(np.median(errs)) if errs.size else float("nan")
    mean = float(errs.mean()) if errs.size else float("nan")
    try:
        record = json.loads((Path(path).parent / SETTINGS_FILENAME).read_text())
        refined = record.get("focal_lengths_refined", record["model_settings"].get("refine_focal_length"))
        held = "poses held fixed, focal lengths refined" if refined else "poses and intrinsics held fixed"
    except (OSError, ValueError, KeyError, TypeError):
        held = "poses held fixed"
    return (
        f"model: {path}\n"
        f"images: {counts.num_reg_images}  cameras: {counts.num_cameras}  points: {counts.num_points3D}  "
        f"observations: {errs.size}\n"
        f"reprojection error: median {_num(median, '.3f')} px, mean {_num(mean, '.3f')} px ({held})"
    )


def report_reconstruct(result) -> str:
    lines = [
        f"workspace: {result.workspace_path}",
        f"images registered: {result.num_registered}/{result.num_images}"
        f"   sparse points: {result.num_points3D}"
        f"   fused points: {result.num_fused_points}",
    ]
    lines += [f"  skipped photo {name}: {why} (not counted)" for name, why in result.skipped_photos.items()]
    lines.append("time per stage:")
    for stage, seconds in result.stage_seconds.items():
        note = "  (already done)" if stage in result.resumed else ""
        lines.append(f"  {stage:<10} {seconds:8.1f} s{note}")
    lines.append(f"  {'total':<10} {sum(result.stage_seconds.values()):8.1f} s")
    lines += [f"  stereo skipped {name}: {why}" for name, why in result.stereo_skipped.items()]
    why_not = f"; the run stopped after {result.stopped_after}" if result.stopped_after else ""
    dense = result.dense_path
    if dense is None:
        dense_line = "  dense workspace: (none)"
    elif dense.is_dir():
        dense_line = f"  dense workspace: {dense}"
    else:
        dense_line = f"  dense workspace: {dense}  (not made yet{why_not})"
    previews = result.previews_path
    if previews is None:
        previews_line = "  previews:        (off; run with --previews true)"
    elif previews.is_dir():
        n_previews = len(list(previews.rglob("*.depth.png")))  # image names may hold folders
        previews_line = (
            f"  previews:        {previews}  ({n_previews} depth maps as PNG, with normals and confidence)"
        )
    else:
        previews_line = f"  previews:        {previews}  (none yet: stereo has not run{why_not})"
    lines += [
        "where to look:",
        f"  sparse model:    {result.sparse_path if result.sparse_path is not None else '(none)'}",
        dense_line,
        previews_line,
        f"  fused cloud:     {result.fused_path if result.fused_path is not None else '(none)'}",
        f"  mesh:            {result.mesh_path if result.mesh_path is not None else '(none)'}",
        f"  pycolmap log:    {result.log_path if result.log_path is not None else '(on the terminal)'}",
    ]
    return "\n".join(lines)


def report_demo(result) -> str:
    lines = [
        f"demo workspace: {result.workspace}  ({result.num_images} images, checkpoint {result.checkpoint})",
        f"depth vs GT: AbsRel {_num(result.depth_absrel)}  MAE {_num(result.depth_mae)}  "
        f"<1%: {_num(result.depth_under_1pct, '.1f')} %  <5%: {_num(result.depth_under_5pct, '.1f')} %  "
        f"coverage {_num(result.depth_coverage_pct, '.1f')} %",
        f"fused cloud: {result.fused_path}  ({result.num_fused_points} points; "
        "median distance to the GT mesh "
        f"{_num(result.cloud_median_error)} of a scene {_num(result.scene_size, '.2f')} across)",
        f"mesh: {result.mesh_path if result.mesh_path is not None else '(failed)'}",
        f"previews: {result.previews}",
        "time: "
        + ", ".join(f"{k} {v:.1f} s" for k, v in result.stage_seconds.items())
        + f"; total {result.seconds:.1f} s",
    ]
    return "\n".join(lines)

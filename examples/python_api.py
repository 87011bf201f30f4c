"""The pipeline from Python: the same step functions the CLI calls.

    python examples/python_api.py --workspace_path path/to/dense

``path/to/dense`` is a COLMAP dense workspace (the output of ``image_undistorter`` or
``colmap-pvs undistort``). Without one, ``--demo`` builds a small synthetic workspace first.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from colmap_pvs.fusion import FuseConfig, fuse
from colmap_pvs.mesh import MeshConfig, mesh
from colmap_pvs.stereo import PhotometricConfig, StereoConfig, run_stereo
from colmap_pvs.views import SelectViewsConfig, format_selection_table, run_select_views


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--workspace_path", type=Path, default=Path("example_workspace"))
    ap.add_argument("--demo", action="store_true", help="build a synthetic workspace at --workspace_path")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO)

    if args.demo:
        from colmap_pvs.synthetic.workspace import SyntheticWorkspaceConfig, make_synthetic_workspace

        make_synthetic_workspace(args.workspace_path, SyntheticWorkspaceConfig(width=320, height=240))

    # 1. Source views and depth ranges from the sparse points (writes stereo/patch-match.cfg).
    selection = run_select_views(SelectViewsConfig(workspace_path=args.workspace_path, num_views=5))
    print(format_selection_table(selection))

    # 2. PVSNet depth + normal maps in COLMAP's format (the shipped checkpoint by default).
    # One nested config per pass (StereoConfig.photometric, .geometric, .completion, ...); a mapping of
    # flag names works too: config_from_dict(StereoConfig, {"workspace_path": ..., "num_views": 5}).
    result = run_stereo(StereoConfig(workspace_path=args.workspace_path, previews=True,
                                     photometric=PhotometricConfig(num_views=5)))
    print(f"stereo: {len(result.processed)} images, {result.seconds_per_image:.2f} s/image")

    # 3. Fusion (ours; method="colmap" runs COLMAP's stereo_fusion on the same maps) and a mesh.
    fused = fuse(FuseConfig(workspace_path=args.workspace_path))
    print(f"fused {fused.num_points} points -> {fused.output_path}")
    print(f"mesh -> {mesh(MeshConfig(input_path=fused.output_path))}")


if __name__ == "__main__":
    main()

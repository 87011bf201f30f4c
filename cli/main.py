"""``colmap-pvs`` command line: a thin front end over the library's step functions.

Every subcommand builds the step's frozen config from flags generated out of that
config dataclass (so defaults live in one place) and calls the same library function
a Python user would call. Installed as ``colmap_pvs.cli`` (never as a top-level ``cli``).
"""

# ruff: noqa: E402 (the imports below come after OpenMP's environment is set)

from __future__ import annotations

import os

from colmap_pvs.openmp import set_wait_env

# How OpenMP's threads wait (colmap_pvs.openmp): set before torch is imported (the CLI is an entry point).
set_wait_env(os.environ)

import argparse
import difflib
import importlib
import logging
import sys
from collections.abc import Callable
from dataclasses import dataclass

from colmap_pvs import __version__
from colmap_pvs.cli.colmap_flags import add_colmap_flags, translate_colmap_flags
from colmap_pvs.config import (
    add_config_arguments,
    config_flags,
    config_from_dict,
    flags_to_dict,
    merge_configs,
    read_config_file,
    removed_options,
)
from colmap_pvs.errors import ColmapPVSError, ConfigError

logger = logging.getLogger("colmap_pvs.cli")


@dataclass(frozen=True)
class Command:
    """One subcommand: ``module:ConfigClass`` and ``module:function`` (imported lazily)."""

    name: str
    help: str
    config: str | None = None
    function: str | None = None
    report: str | None = None
    planned: str | None = None  # set while the command is not built yet
    required: tuple[str, ...] = ()
    positional: tuple[str, ...] = ()  # config fields also accepted as optional positionals
    aliases: tuple[str, ...] = ()  # e.g. COLMAP's own command name


COMMANDS: tuple[Command, ...] = (
    Command(
        "undistort",
        "undistort a sparse model + images into a dense workspace (pycolmap)",
        "colmap_pvs.io.workspace:UndistortConfig",
        "colmap_pvs.io.workspace:undistort",
        required=("image_path", "input_path", "output_path"),
    ),
    Command(
        "select-views",
        "score source views (MVSNet score) and depth ranges; writes stereo/patch-match.cfg",
        "colmap_pvs.views:SelectViewsConfig",
        "colmap_pvs.views:run_select_views",
        "colmap_pvs.cli.reports:report_select_views",
        required=("workspace_path",),
    ),
    Command(
        "stereo",
        "PVSNet depth + normal maps in COLMAP's format (replaces patch_match_stereo)",
        "colmap_pvs.stereo:StereoConfig",
        "colmap_pvs.adapt:run_adapted_stereo",  # run_stereo, after the adaptation when --adapt_steps > 0
        "colmap_pvs.cli.reports:report_stereo",
        required=("workspace_path",),
        aliases=("patch_match_stereo",),
    ),
    Command(
        "fuse",
        "fuse depth maps into a point cloud + .vis (ours: geometric consistency; or COLMAP's)",
        "colmap_pvs.fusion:FuseConfig",
        "colmap_pvs.fusion:fuse",
        "colmap_pvs.cli.reports_pipeline:report_fuse",
        required=("workspace_path",),
    ),
    Command(
        "mesh",
        "screened Poisson mesh from a fused cloud, trimmed by density (open3d or COLMAP)",
        "colmap_pvs.mesh:MeshConfig",
        "colmap_pvs.mesh:mesh",
        "colmap_pvs.cli.reports_pipeline:report_mesh",
        required=("input_path",),
    ),
    Command(
        "reconstruct",
        "images -> SfM -> undistort -> stereo -> fusion -> mesh, in one resumable command (CPU)",
        "colmap_pvs.reconstruct:ReconstructConfig",
        "colmap_pvs.reconstruct:reconstruct",
        "colmap_pvs.cli.reports_pipeline:report_reconstruct",
        required=("image_path", "workspace_path"),
    ),
    Command(
        "import-poses",
        "known poses -> COLMAP model with triangulated points (poses fixed; focal refined from 10 images)",
        "colmap_pvs.io.import_poses:ImportPosesConfig",
        "colmap_pvs.io.import_poses:import_poses",
        "colmap_pvs.cli.reports_pipeline:report_import_poses",
        required=("image_path", "poses_path", "output_path"),
    ),
    Command(
        "demo",
        "run the whole pipeline on a built-in synthetic scene: colmap-pvs demo [OUT]",
        "colmap_pvs.demo:DemoConfig",
        "colmap_pvs.demo:run_demo",
        "colmap_pvs.cli.reports_pipeline:report_demo",
        positional=("output_path",),
    ),
    Command(
        "train",
        "train PVSNet on synthetic scenes, optionally mixed with real COLMAP scenes (self-supervised, "
        "--real_fraction); anti-noise strategy; resumable from OUTPUT_DIR/last.pt",
        "colmap_pvs.train:TrainConfig",
        "colmap_pvs.train:train",
        "colmap_pvs.cli.reports:report_checkpoint",
    ),
    Command(
        "average-weights",
        "weighted average of PVSNet checkpoints (weights and their fine-tune: a 'model soup')",
        "colmap_pvs.average_weights:AverageWeightsConfig",
        "colmap_pvs.average_weights:average_weights",
        "colmap_pvs.cli.reports:report_checkpoint",
        required=("checkpoints", "output_path"),
    ),
    Command(
        "evaluate depth",
        "depth-map metrics (coverage, MAE, RMSE, AbsRel, % under thresholds) against GT depth",
        "colmap_pvs.evaluate:EvaluateDepthConfig",
        "colmap_pvs.evaluate:evaluate_depth",
        "colmap_pvs.cli.reports_eval:report_depth",
        required=("workspace_path", "gt"),
    ),
    Command(
        "evaluate cloud",
        "point-cloud accuracy / completeness / F1 (ETH3D-style) and DTU distances against a GT cloud",
        "colmap_pvs.evaluate:EvaluateCloudConfig",
        "colmap_pvs.evaluate:evaluate_cloud",
        "colmap_pvs.cli.reports_eval:report_cloud",
        required=("cloud", "gt"),
    ),
)


def _load(ref: str):
    module, _, attr = ref.partition(":")
    return getattr(importlib.import_module(module), attr)


class _Parser(argparse.ArgumentParser):
    """An argparse parser whose errors are one line naming the flag (no usage dump)."""

    def __init__(self, *args, **kwargs) -> None:
        kwargs.setdefault("allow_abbrev", False)  # `--num_view 3` is a mistake, not --num_views
        super().__init__(*args, **kwargs)

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="colmap-pvs",
        description="Learned dense multi-view stereo (PVSNet) for COLMAP workspaces, CPU first.",
    )
    parser.add_argument("--version", action="version", version=f"colmap-pvs {__version__}")
    parser.add_argument("--log_level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"])
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    groups: dict[str, argparse._SubParsersAction] = {}
    parser.by_command = {}  # command name -> its parser (for the hints of unrecognized flags)
    for cmd in COMMANDS:
        help_text = cmd.help if cmd.planned is None else f"{cmd.help} [not built yet: {cmd.planned}]"
        help_text = help_text.replace("%", "%%")  # argparse %-formats help texts
        group, _, leaf = cmd.name.rpartition(" ")
        if group:  # nested, e.g. "evaluate depth"
            if group not in groups:
                gp = sub.add_parser(group, help=f"{group} subcommands")
                groups[group] = gp.add_subparsers(dest=f"{group}_command", metavar="SUBCOMMAND",
                                                  required=True)
            p = groups[group].add_parser(leaf, help=help_text, description=help_text)
        else:
            p = sub.add_parser(cmd.name, help=help_text, description=help_text)
        parser.by_command[cmd.name] = p
        _add_command_flags(p, cmd, colmap_help=False)
        for alias in cmd.aliases:  # COLMAP's name: the same flags, and its --help lists COLMAP's own
            a = sub.add_parser(alias, help=f"{cmd.name} under COLMAP's name; accepts COLMAP's flags",
                               description=help_text)
            _add_command_flags(a, cmd, colmap_help=True)
    return parser


def _add_command_flags(p: argparse.ArgumentParser, cmd: Command, colmap_help: bool) -> None:
    """The flags of ``cmd``'s config (one group per nested config) on its parser ``p``."""
    p.set_defaults(command=cmd.name)
    # a short usage line; the flags follow, grouped, one line each with its default
    p.formatter_class = lambda prog: argparse.HelpFormatter(prog, max_help_position=42, width=160)
    p.usage = " ".join(["%(prog)s", *(f"--{r} {r.upper()}" for r in cmd.required), "[options]",
                        *(f"[{n.upper()}]" for n in cmd.positional)])
    if cmd.config is not None:
        add_config_arguments(p, _load(cmd.config), required=cmd.required)
        p.add_argument(
            "--config_file",
            dest="_config_file",
            default=None,
            metavar="JSON",
            help="JSON of config values (by name or nested; a saved config's \"base\": a file it changes); "
            "flags override it",
        )
    for name in cmd.positional:  # e.g. `demo [OUT]`; the --flag form keeps working
        p.add_argument(name, nargs="?", default=argparse.SUPPRESS, metavar=name.upper(),
                       help=f"same as --{name}")
    if cmd.aliases:  # COLMAP's patch_match_stereo flags: accepted by both, listed by COLMAP's name only
        add_colmap_flags(p, listed=colmap_help)


def _build_config(config_cls: type, args: argparse.Namespace):
    """Config from ``--config_file`` (if given) overridden by the flags given on the command line."""
    flags = set(config_flags(config_cls)) | set(removed_options(config_cls))
    given = {k: v for k, v in vars(args).items() if k in flags}
    if args._config_file is None:
        return config_from_dict(config_cls, given)
    where = f"--config_file {str(args._config_file)!r}"
    data = read_config_file(config_cls, args._config_file, where=where)
    try:
        return config_from_dict(config_cls, merge_configs(data, flags_to_dict(config_cls, given)))
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from None


def _unknown_flags(parser: argparse.ArgumentParser, args: argparse.Namespace, extra: list[str]) -> str:
    """One line for the arguments no parser took, with the nearest flag of the command."""
    p = parser.by_command.get(getattr(args, "command", None), parser)
    known = [o for a in p._actions for o in a.option_strings if o.startswith("--")]
    bad = next((e for e in extra if e.startswith("-")), extra[0]).split("=")[0]
    near = difflib.get_close_matches("--" + bad.lstrip("-").replace("-", "_"), known, n=1, cutoff=0.75)
    hint = f"; did you mean {near[0]}?" if near else ""
    return f"{p.prog}: error: unrecognized argument {bad!r}{hint} (see '{p.prog} --help')\n"


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if extra:
        sys.stderr.write(_unknown_flags(parser, args, extra))
        return 2
    logging.basicConfig(level=args.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if args.command is None:
        parser.print_help()
        return 2
    cmd = next(c for c in COMMANDS if c.name == args.command)
    if cmd.planned is not None:
        sys.stderr.write(f"colmap-pvs {cmd.name}: not built yet (planned in {cmd.planned}).\n")
        return 2
    config_cls = _load(cmd.config)
    function: Callable = _load(cmd.function)
    try:
        if cmd.aliases:
            for key, value in translate_colmap_flags(args).items():
                setattr(args, key, value)
        config = _build_config(config_cls, args)
        result = function(config)
    except ColmapPVSError as exc:
        sys.stderr.write(f"colmap-pvs {cmd.name}: error: {exc}\n")
        return 1
    except OSError as exc:  # read-only folder, disk full, ...: one line naming the file, no traceback
        sys.stderr.write(f"colmap-pvs {cmd.name}: error: {exc}\n")
        return 1
    except KeyboardInterrupt as exc:  # includes training's TrainingInterrupted (state saved)
        sys.stderr.write(f"colmap-pvs {cmd.name}: interrupted{': ' + str(exc) if str(exc) else ''}\n")
        return 130
    if cmd.report is not None:
        sys.stdout.write(_load(cmd.report)(result) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

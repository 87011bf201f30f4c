"""The ``reconstruct`` step: a folder of photos -> sparse model -> depth maps -> point cloud -> mesh.

Stages (all on the CPU), each skipped when its finished output already exists, so a stopped
run resumes where it stopped::

    features   SIFT (pycolmap.extract_features)      WORKSPACE/database.db  (+ .done marker)
    matching   exhaustive (<= exhaustive_max_images) or sequential           (+ .done marker)
    mapping    incremental SfM (pycolmap.incremental_mapping)  WORKSPACE/sparse/0
    undistort  colmap_pvs.io.workspace.undistort                WORKSPACE/dense
    stereo     colmap_pvs.adapt.run_adapted_stereo (run_stereo, per-image resumable)  WORKSPACE/dense/stereo
    fusion     colmap_pvs.fusion.fuse                           WORKSPACE/dense/fused.ply(.vis)
    mesh       colmap_pvs.mesh.mesh                             WORKSPACE/dense/meshed-poisson.ply

With ``input_path`` (an existing sparse model of ``image_path``) the first three stages are
skipped. Markers live in ``WORKSPACE/.colmap_pvs/``; outputs are written atomically by each step.

Provenance: each finished stage's marker records the settings (and the photos and checkpoint content)
it was made with (:data:`STAGE_SETTINGS`). A rerun whose settings differ for a finished stage is
refused with a message naming the setting, both values and the stages it affects; with
``overwrite`` that stage and the ones after it are recomputed (with no setting changed, ``overwrite``
recomputes every stage). pycolmap's log goes to ``WORKSPACE/logs/`` (unless the ``colmap_pvs``
logger is at DEBUG) and every SfM stage has a progress bar.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from .confidence import calibration_path, load_calibration
from .config import check_threads, config_json_bytes, config_to_dict, replace_config
from .errors import ConfigError, WorkspaceError
from .fusion.config import FUSION_RULES
from .io.cleanup import remove_orphan_temps
from .io.files import atomic_write_bytes, cached_file_hashes, file_sha256, files_state_sha256, remove_database
from .io.images import check_image_file, check_image_format
from .io.workspace import fusion_inputs_sha256, set_aside_foreign_output
from .stereo.config import FORMAT_VERSIONS, StereoConfig, map_settings

logger = logging.getLogger(__name__)

__all__ = ["ReconstructConfig", "ReconstructResult", "reconstruct", "STAGES"]

STAGES = ("features", "matching", "mapping", "undistort", "stereo", "fusion", "mesh")
#: The settings each stage's output depends on ("photos": names, sizes and content of the photos;
#: "model": the sparse model given with ``input_path``; "checkpoint_sha256": the checkpoint's content, so
#: a moved copy of the same weights is the same checkpoint and new weights at the same path are not;
#: "calibration_sha256": its confidence calibration's, ``colmap_pvs.confidence.calibration_path``).
STAGE_SETTINGS: dict[str, tuple[str, ...]] = {
    "features": (
        "photos",
        "camera_model",
        "single_camera",
        "max_num_features",
        "sift_peak_threshold",
        "sift_max_image_size",
    ),
    "matching": ("matcher", "exhaustive_max_images"),
    "mapping": (),
    "undistort": ("photos", "input_path", "undistort_max_image_size"),
    # every stereo setting that changes the maps, and the weights by their content, wherever they are
    "stereo": ("stereo", "checkpoint_sha256", "calibration_sha256", "stereo_formats"),
    "fusion": ("fusion_method", "fusion_rules"),
    "mesh": ("mesh", "mesh_depth"),
}
_IMAGE_EXTENSIONS = {".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".ppm", ".pgm"}


@dataclass(frozen=True)
class ReconstructConfig:
    """Settings of ``reconstruct`` (the single source of its defaults and CLI flags)."""

    image_path: Path = field(metadata={"help": "folder with the photos"})
    workspace_path: Path = field(metadata={"help": "output folder (database.db, sparse/0, dense/)"})
    input_path: Path | None = field(
        default=None,
        metadata={"help": "existing sparse model of these images: skip feature/matching/mapping"},
    )
    camera_model: str = field(default="SIMPLE_RADIAL", metadata={"help": "COLMAP camera model for SfM"})
    single_camera: bool = field(default=False, metadata={"help": "all images share one camera"})
    max_num_features: int = field(default=4096, metadata={"help": "SIFT features per image"})
    sift_peak_threshold: float = field(
        default=0.0067,
        metadata={"help": "SIFT peak (contrast) threshold (COLMAP's default); lower finds more keypoints"},
    )
    sift_max_image_size: int = field(
        default=1600, metadata={"help": "SIFT runs on images downscaled to this longest side"}
    )
    matcher: Literal["auto", "exhaustive", "sequential"] = field(
        default="auto",
        metadata={"help": "auto: exhaustive up to exhaustive_max_images images, else sequential"},
    )
    exhaustive_max_images: int = field(default=50, metadata={"help": "auto matcher threshold"})
    undistort_max_image_size: int = field(
        default=-1, metadata={"help": "longest side of the undistorted images; -1 keeps the size"}
    )
    fusion_method: Literal["pvs", "colmap"] = field(default="pvs", metadata={"help": "fusion method"})
    mesh: bool = field(default=True, metadata={"help": "build a Poisson mesh of the fused cloud"})
    mesh_depth: int = field(default=9, metadata={"help": "Poisson octree depth"})
    num_threads: int = field(default=-1, metadata={"help": "CPU threads for SfM and meshing; -1 = all"})
    overwrite: bool = field(
        default=False,
        metadata={
            "help": "recompute the stages whose settings changed and those after (none changed: all)"
        },
    )
    stop_after: Literal["features", "matching", "mapping", "undistort", "stereo", "fusion", "mesh"] | None = (
        field(
            default=None,
            metadata={"help": "stop after this stage (a rerun goes on)"},
        )
    )
    stereo: StereoConfig = field(
        default_factory=lambda: StereoConfig(workspace_path=Path("dense"), previews=True),
        metadata={"flag_prefix": "", "title": "stereo", "exclude_flags": ("workspace_path", "overwrite"),
                  "help": "the stereo step's settings (its workspace is WORKSPACE/dense)"},
    )

    def __post_init__(self) -> None:
        if self.max_num_features < 16:
            raise ConfigError(f"max_num_features must be >= 16, got {self.max_num_features}")
        if not 0.0 < self.sift_peak_threshold < 1.0:
            raise ConfigError(f"sift_peak_threshold must be in (0, 1), got {self.sift_peak_threshold}")
        if self.exhaustive_max_images < 2:
            raise ConfigError(f"exhaustive_max_images must be >= 2, got {self.exhaustive_max_images}")
        check_threads("num_threads", self.num_threads, auto=-1)
        if not 1 <= self.mesh_depth <= 16:
            raise ConfigError(f"mesh_depth must be in [1, 16], got {self.mesh_depth}")


@dataclass
class ReconstructResult:
    """Summary of a :func:`reconstruct` run.

    Attributes:
        num_images: photos in ``image_path``; num_registered: images in the sparse model.
        num_points3D: sparse points; num_fused_points: points of the fused cloud.
        stage_seconds: wall time of each stage run now (``0`` for a stage that was already done).
        resumed: stages whose finished output was found and reused.
        sparse_path, dense_path, fused_path, mesh_path: outputs (``mesh_path`` ``None`` without mesh).
        stereo_skipped: images stereo skipped, with the reason.
        skipped_photos: files of ``image_path`` that are not readable images (e.g. a text file named
            ``IMG_0001.jpg``), left out before SfM, with the reason; not counted in ``num_images``.
        previews_path: the folder of depth / normal / confidence PNGs (``None`` with previews off and
            none written); set before the stages run, so it may not exist yet (see ``stopped_after``).
        stopped_after: the ``stop_after`` stage of the run (``None``: it ran to the end).
        log_path: the folder of pycolmap's log (``None`` when it went to the terminal).
    """

    workspace_path: Path
    sparse_path: Path | None = None
    dense_path: Path | None = None
    fused_path: Path | None = None
    mesh_path: Path | None = None
    num_images: int = 0
    num_registered: int = 0
    num_points3D: int = 0
    num_fused_points: int = 0
    stage_seconds: dict[str, float] = field(default_factory=dict)
    resumed: list[str] = field(default_factory=list)
    stereo_skipped: dict[str, str] = field(default_factory=dict)
    skipped_photos: dict[str, str] = field(default_factory=dict)
    previews_path: Path | None = None
    stopped_after: str | None = None
    log_path: Path | None = None


def _list_images(folder: Path) -> list[str]:
    return sorted(
        str(p.relative_to(folder))
        for p in folder.rglob("*")
        if p.is_file() and p.suffix.lower() in _IMAGE_EXTENSIONS and not p.name.startswith(".")
    )


class _Progress:
    """Per-stage timing, logging, done-markers (with the settings each stage was made with)."""

    def __init__(self, root: Path, result: ReconstructResult) -> None:
        self.markers = root / ".colmap_pvs"
        self.result = result
        self.settings: dict[str, dict] = {}  # stage -> the settings its output is made with
        self.overwrite: set[str] = set()  # stages whose old output must not be resumed
        self._t = 0.0
        self._stage = ""

    def done(self, stage: str) -> bool:
        return stage not in self.overwrite and (self.markers / f"{stage}.done").is_file()

    def mark(self, stage: str, **extra) -> None:
        """Mark ``stage`` finished, with its settings and ``extra`` (``inputs``: what it read)."""
        payload = {"stage": stage, "settings": self.settings.get(stage, {}), **extra}
        atomic_write_bytes(self.markers / f"{stage}.done", (json.dumps(payload, indent=1) + "\n").encode())

    def unmark(self, *stages: str) -> None:
        for stage in stages:
            (self.markers / f"{stage}.done").unlink(missing_ok=True)

    def recorded(self, stage: str, key: str = "settings"):
        """What a finished stage recorded under ``key`` (its settings, or the ``inputs`` it read);
        ``None`` when unknown (no marker, or an old one)."""
        try:
            payload = json.loads((self.markers / f"{stage}.done").read_text())
        except (OSError, ValueError):
            return None
        return payload.get(key) if isinstance(payload, dict) else None

    def start(self, stage: str) -> None:
        self._stage, self._t = stage, time.perf_counter()
        logger.info("reconstruct [%d/%d] %s ...", STAGES.index(stage) + 1, len(STAGES), stage)

    def stop(self) -> None:
        seconds = time.perf_counter() - self._t
        self.result.stage_seconds[self._stage] = seconds
        logger.info("reconstruct: %s done in %.1f s", self._stage, seconds)

    def skip(self, stage: str, why: str) -> None:
        self.result.stage_seconds[stage] = 0.0
        self.result.resumed.append(stage)
        logger.info("reconstruct [%d/%d] %s: %s", STAGES.index(stage) + 1, len(STAGES), stage, why)


def _model_dir_ok(path: Path) -> bool:
    return all(
        (path / f"{n}.bin").is_file() or (path / f"{n}.txt").is_file()
        for n in ("cameras", "images", "points3D")
    )


# --------------------------------------------------------------------------- provenance


#: The photos' hashes of the last run, by name, size and modification time (a resume reads no photo again).
PHOTO_HASHES = "photos_sha256.json"


def _photos_fingerprint(hashes: dict[str, list]) -> dict:
    """The photos' names and sizes (``sha256``) and their content (``content_sha256``: a photo edited in
    place, same size and name, is a change too)."""
    digest, content = hashlib.sha256(), hashlib.sha256()
    for name, (size, _, sha) in hashes.items():
        digest.update(f"{name}\0{size}\n".encode())
        content.update(f"{name}\0{sha}\n".encode())
    return {"count": len(hashes), "sha256": digest.hexdigest(), "content_sha256": content.hexdigest()}


def _photos_differ(old, new: dict) -> bool:
    """A record of an older colmap-pvs has no ``content_sha256``: its names and sizes are compared.
    Back-compat (dropped in 0.3): the markers in a user's workspace may be such a record."""
    if not isinstance(old, dict):
        return old != new
    key = "content_sha256" if "content_sha256" in old else "sha256"
    return old.get("count") != new["count"] or old.get(key) != new[key]


#: What the stereo stage recorded before it recorded every stereo setting (an older colmap-pvs).
#: Back-compat (dropped in 0.3): the stereo marker in a user's workspace may hold only these.
LEGACY_STEREO_KEYS = ("max_image_size", "num_views", "network_scale")


def _remove_stale(path: Path) -> None:
    """Remove an output of ours that new maps make stale; one COLMAP or the user wrote under the same
    name (``dense/fused.ply``, ``meshed-poisson.ply``) is kept as ``.bak`` instead."""
    if set_aside_foreign_output(path) is None:
        path.unlink(missing_ok=True)


def _sha256_or_none(path: Path) -> str | None:
    return file_sha256(path) if path.is_file() else None


def _calibration_sha256(checkpoint: Path) -> str | None:
    """Hash of the curves of ``checkpoint``'s confidence calibration (what its confidence maps depend
    on); ``None`` without one."""
    path = calibration_path(checkpoint)
    return load_calibration(path).sha256() if path.is_file() else None


def _current_settings(config: ReconstructConfig, photos: dict[str, list],
                      checkpoint: Path) -> dict[str, dict]:
    values = {
        "photos": _photos_fingerprint(photos),
        "input_path": str(Path(config.input_path).resolve()) if config.input_path is not None else None,
        "checkpoint_sha256": _sha256_or_none(checkpoint),
        "calibration_sha256": _calibration_sha256(checkpoint),
        **{k: v for k, v in config_to_dict(config).items() if k not in ("input_path", "stereo")},
        "stereo": map_settings(config.stereo),  # a run-only flag (threads, Ray, previews) resumes
        # the maps' formats: a new colmap-pvs may write some pass differently (the stereo step resumes)
        "stereo_formats": dict(FORMAT_VERSIONS),
        "fusion_rules": FUSION_RULES,  # likewise: a cloud of other rules is fused again
    }
    return {stage: {key: values[key] for key in keys} for stage, keys in STAGE_SETTINGS.items()}


def _describe_change(key: str, old, new) -> str:
    if key == "photos":
        return f"the photos ({old.get('count')} -> {new.get('count')} files; names, sizes or content changed)"
    if key == "stereo":
        changed = [f"--{k} {old.get(k)} -> {v}" for k, v in new.items() if k in old and old[k] != v]
        return "stereo settings " + ", ".join(changed)
    if key == "checkpoint_sha256":
        return f"the checkpoint's content (sha256 {str(old)[:12]} -> {str(new)[:12]})"
    if key == "calibration_sha256":
        return f"the checkpoint's confidence calibration (sha256 {str(old)[:12]} -> {str(new)[:12]})"
    return f"{key} {old} -> {new}"


def _check_provenance(config: ReconstructConfig, prog: _Progress, root: Path) -> None:
    """Refuse (or, with ``overwrite``, schedule the recomputation of) stages made with other settings."""
    changes: list[tuple[str, str]] = []  # (stage, description)
    formats_changed = rules_changed = False
    for stage in STAGES:
        recorded = prog.recorded(stage)
        if recorded is None:
            continue
        if stage == "stereo" and "stereo" not in recorded:  # an older marker: its flat stereo settings
            recorded = {**recorded, "stereo": {k: recorded[k] for k in LEGACY_STEREO_KEYS
                                               if k in recorded}}
        for key, new in prog.settings[stage].items():
            old = recorded.get(key)
            if key == "stereo" and isinstance(old, dict):  # a setting it did not record: not changed
                differs = any(k in old and old[k] != v for k, v in new.items())
            elif key == "calibration_sha256":  # recorded since the confidence is calibrated; before: none
                differs = old != new
            elif key == "photos" and key in recorded:
                differs = _photos_differ(old, new)
            elif key == "stereo_formats":  # not a setting: stereo resumes (redoing what changed)
                if old != new:
                    formats_changed = True
                continue
            elif key == "fusion_rules":  # not a setting either: fusion and mesh are made again
                rules_changed |= old != new
                continue
            else:
                differs = key in recorded and old != new
            if differs:
                changes.append((stage, _describe_change(key, recorded.get(key), new)))
    if changes:
        first = min(STAGES.index(stage) for stage, _ in changes)
        redo = STAGES[first:]
        listed = "; ".join(f"{what} ({stage})" for stage, what in changes)
        if not config.overwrite:
            raise ConfigError(
                f"workspace {str(root)!r} was made with other settings: {listed}; pass --overwrite to "
                f"recompute {', '.join(redo)}, or use another --workspace_path"
            )
        logger.warning("reconstruct: settings changed (%s): recomputing %s", listed, ", ".join(redo))
    elif config.overwrite:
        redo = STAGES[3:] if config.input_path is not None else STAGES
        logger.info("reconstruct: --overwrite: recomputing %s", ", ".join(redo))
    elif formats_changed:
        logger.info("reconstruct: the depth maps are from an older colmap-pvs: resuming stereo (it "
                    "recomputes the passes whose format changed), then fusion and mesh")
        prog.unmark("stereo", "fusion", "mesh")
        return
    elif rules_changed:
        logger.info("reconstruct: the cloud was fused by an older colmap-pvs: fusing and meshing again")
        prog.unmark("fusion", "mesh")
        return
    else:
        return
    prog.overwrite = set(redo)
    prog.unmark(*redo)


def _check_photos(folder: Path, names: list[str]) -> None:
    problems = []
    for name in names:
        try:
            check_image_file(folder / name)
        except WorkspaceError as exc:
            problems.append(str(exc))
    if problems:
        raise WorkspaceError(
            f"{len(problems)} of {len(names)} photos in {str(folder)!r} cannot be used (remove or replace "
            f"them): {'; '.join(problems[:5])}{' ...' if len(problems) > 5 else ''}"
        )


def _readable_photos(folder: Path, names: list[str]) -> tuple[list[str], dict[str, str]]:
    """The photos an image decoder recognises, and the others (named, with the reason), logged as
    skipped photos in one warning: COLMAP would silently fail to read them and report them as not
    registered."""
    kept: list[str] = []
    skipped: dict[str, str] = {}
    for name in names:
        try:
            check_image_format(folder / name)
        except WorkspaceError:
            skipped[name] = "not a readable image (no image decoder recognises its content)"
            continue
        kept.append(name)
    if skipped:
        listed = ", ".join(list(skipped)[:3]) + (f" and {len(skipped) - 3} more" if len(skipped) > 3 else "")
        logger.warning("reconstruct: skipping %d file(s) that are no readable image: %s; remove them from %s "
                       "or replace them with photos", len(skipped), listed, folder)
    return kept, skipped


# --------------------------------------------------------------------------- SfM


def _run_sfm(
    config: ReconstructConfig, root: Path, names: list[str], prog: _Progress, stop_after: str | None
) -> Path | None:
    """Features, matching and mapping; ``None`` when ``stop_after`` stopped it before a model exists."""
    from .io.features import clear_matches, extract_features, match_features, resolve_matcher
    from .io.sfm import incremental_mapping

    image_dir = Path(config.image_path)
    db = root / "database.db"
    sparse = root / "sparse" / "0"
    if _model_dir_ok(sparse) and not prog.overwrite & {"features", "matching", "mapping"}:
        for stage in ("features", "matching", "mapping"):
            prog.skip(stage, f"model found in {sparse}")
        return sparse

    if prog.done("features") and db.is_file():
        prog.skip("features", "already extracted")
    else:
        prog.start("features")
        prog.unmark("matching")
        prog.overwrite.discard("matching")  # a new database has no matches to forget
        staged = root / "database.db.new"  # replaces the old database once complete
        remove_database(staged)
        try:
            extract_features(staged, image_dir, names, camera_model=config.camera_model,
                             single_camera=config.single_camera, num_threads=config.num_threads,
                             max_image_size=config.sift_max_image_size,
                             max_num_features=config.max_num_features,
                             peak_threshold=config.sift_peak_threshold, progress=True)
        except BaseException:
            remove_database(staged)
            raise
        for journal in (f"{db}-wal", f"{db}-shm"):  # the old database's; os.replace swaps the file itself
            Path(journal).unlink(missing_ok=True)
        os.replace(staged, db)
        prog.mark("features")
        prog.stop()
    if stop_after == "features":
        return None

    if prog.done("matching"):
        prog.skip("matching", "already matched")
    else:
        prog.start("matching")
        if "matching" in prog.overwrite:
            clear_matches(db)
        use = resolve_matcher(config.matcher, len(names), config.exhaustive_max_images)
        logger.info("reconstruct: %s matching of %d images", use, len(names))
        match_features(db, use, num_images=len(names), num_threads=config.num_threads, progress=True)
        prog.mark("matching")
        prog.stop()
    if stop_after == "matching":
        return None

    prog.start("mapping")
    incremental_mapping(
        db, image_dir, sparse, num_threads=config.num_threads, num_images=len(names), work_dir=root
    )
    prog.mark("mapping")
    prog.stop()
    return sparse


def reconstruct(config: ReconstructConfig) -> ReconstructResult:
    """Run the whole pipeline (see the module docstring); resumable.

    Raises:
        WorkspaceError: no images, unusable photos (empty, truncated), SfM failure, or a failure of a
            later step (named by that step).
        ConfigError: a finished stage was made with other settings and ``overwrite`` is not set.
        CheckpointError: no checkpoint given and none shipped.
    """
    from .stereo.config import DEFAULT_CHECKPOINT

    image_dir = Path(config.image_path)
    root = Path(config.workspace_path)
    if not image_dir.is_dir():
        raise WorkspaceError(f"image folder {str(image_dir)!r} does not exist")
    names = _list_images(image_dir)
    if len(names) < 2:
        raise WorkspaceError(
            f"image folder {str(image_dir)!r} has {len(names)} image(s); at least 2 are needed"
        )
    needs_stereo = config.stop_after not in ("features", "matching", "mapping", "undistort")
    if needs_stereo and config.stereo.checkpoint is None and not Path(DEFAULT_CHECKPOINT).is_file():
        from .errors import CheckpointError

        raise CheckpointError(
            f"no trained default checkpoint is shipped at {str(DEFAULT_CHECKPOINT)!r}; pass --checkpoint PATH"
        )
    _check_photos(image_dir, names)
    names, skipped_photos = _readable_photos(image_dir, names)
    if len(names) < 2:
        raise WorkspaceError(
            f"image folder {str(image_dir)!r} has {len(names)} readable image(s); at least 2 are needed "
            f"(skipped: {', '.join(skipped_photos)})"
        )
    dense = root / "dense"
    previews = dense / "stereo" / "previews"
    result = ReconstructResult(
        workspace_path=root,
        dense_path=dense,
        num_images=len(names),
        skipped_photos=skipped_photos,
        previews_path=previews if config.stereo.previews or previews.is_dir() else None,
        stopped_after=config.stop_after,
    )
    prog = _Progress(root, result)
    checkpoint = Path(config.stereo.checkpoint or DEFAULT_CHECKPOINT)
    photos = cached_file_hashes(Path(config.image_path), names, prog.markers / PHOTO_HASHES)
    prog.settings = _current_settings(config, photos, checkpoint)
    _check_provenance(config, prog, root)  # before anything is written
    root.mkdir(parents=True, exist_ok=True)
    remove_orphan_temps(root)
    remove_orphan_temps(prog.markers)
    prog.markers.mkdir(exist_ok=True)
    atomic_write_bytes(prog.markers / PHOTO_HASHES, json.dumps(photos).encode())
    atomic_write_bytes(root / "colmap_pvs_reconstruct.json", config_json_bytes(config))
    from .io.pycolmap_output import (  # pycolmap itself is imported only inside io/
        pycolmap_log_to_file,
    )

    quiet = not logging.getLogger("colmap_pvs").isEnabledFor(logging.DEBUG)
    with pycolmap_log_to_file(root / "logs", enabled=quiet) as log_dir:
        result.log_path = log_dir
        _reconstruct(config, root, names, prog, result)
    return result


def _reconstruct(
    config: ReconstructConfig, root: Path, names: list[str], prog: _Progress, result: ReconstructResult
) -> None:
    from .adapt import run_adapted_stereo  # run_stereo, after test-time adaptation with adapt_steps
    from .fusion import FuseConfig, fuse
    from .io.ply import cloud_pair_is_complete, read_point_cloud, vis_path_of
    from .io.sfm import model_counts
    from .io.workspace import UndistortConfig, detect_workspace, undistort
    from .mesh import DEFAULT_MESH_NAME, MeshConfig, mesh

    image_dir = Path(config.image_path)
    total = time.perf_counter()
    if config.input_path is not None:
        sparse = Path(config.input_path)
        if not _model_dir_ok(sparse):
            raise WorkspaceError(
                f"--input_path {str(sparse)!r} holds no COLMAP model (cameras/images/points3D)"
            )
        for stage in ("features", "matching", "mapping"):
            prog.skip(stage, f"using the existing model {sparse}")
    else:
        sparse = _run_sfm(config, root, names, prog, config.stop_after)
        if sparse is None:
            return
        if "mapping" not in result.resumed and (root / "dense").exists():
            logger.info("reconstruct: new sparse model; removing the stale dense workspace")
            shutil.rmtree(root / "dense")
    counts = model_counts(sparse)
    result.sparse_path = sparse
    result.num_registered = counts.num_reg_images
    result.num_points3D = counts.num_points3D
    logger.info(
        "reconstruct: sparse model: %d/%d images registered, %d points",
        result.num_registered,
        len(names),
        result.num_points3D,
    )
    if result.num_registered < len(names):
        logger.warning("reconstruct: %d image(s) were not registered", len(names) - result.num_registered)
    if config.stop_after == "mapping":
        return

    dense = root / "dense"
    fused = dense / "fused.ply"
    meshed = dense / DEFAULT_MESH_NAME
    result.dense_path = dense
    staged, old = root / f".{dense.name}.new", root / f".{dense.name}.old"  # undistort's swap (below)
    if dense.is_dir():  # what a run killed while swapping left beside a complete workspace
        for leftover in (staged, old):
            shutil.rmtree(leftover, ignore_errors=True)
    have_dense = "undistort" not in prog.overwrite
    if have_dense:
        try:
            detect_workspace(dense, create_stereo_dirs=False)
        except WorkspaceError:
            have_dense = False
    if have_dense:
        prog.skip("undistort", f"dense workspace found in {dense}")
    else:
        prog.start("undistort")
        # the new workspace is made beside the old one, which goes only once it is complete
        for leftover in (staged, old):  # of a run killed while swapping
            shutil.rmtree(leftover, ignore_errors=True)
        undistort(
            UndistortConfig(
                image_path=image_dir,
                input_path=sparse,
                output_path=staged,
                max_image_size=config.undistort_max_image_size,
            )
        )
        prog.unmark("stereo", "fusion", "mesh")
        if dense.exists():
            os.replace(dense, old)
        os.replace(staged, dense)
        shutil.rmtree(old, ignore_errors=True)
        prog.mark("undistort")
        prog.stop()
    if config.stop_after == "undistort":
        return

    previews = dense / "stereo" / "previews"
    # what stereo reads besides its settings (by file name, size and time)
    stereo_inputs = files_state_sha256([dense / "images", dense / "sparse", dense / "stereo/patch-match.cfg"])
    if prog.done("stereo") and prog.recorded("stereo", "inputs") != stereo_inputs:
        # the undistorted images, the model or patch-match.cfg changed since (or an older marker without
        # their record): stereo resumes, recomputing the maps whose inputs changed
        logger.info("reconstruct: the images, model or patch-match.cfg in %s changed since the depth maps "
                    "were made (or there is no record of them): resuming stereo", dense)
        prog.unmark("stereo")
    if prog.done("stereo"):
        prog.skip("stereo", "depth maps already computed")
        if config.stereo.previews and not previews.is_dir():  # output-only: the maps stay as they are
            logger.info("reconstruct: writing the previews of the finished depth maps")
            run_adapted_stereo(replace_config(config.stereo, workspace_path=dense))
    else:
        prog.start("stereo")
        for stale in (fused, vis_path_of(fused), meshed):
            _remove_stale(stale)
        prog.unmark("fusion", "mesh")
        st = run_adapted_stereo(replace_config(config.stereo, workspace_path=dense,
                                               overwrite="stereo" in prog.overwrite))
        result.stereo_skipped = dict(st.skipped)
        prog.mark("stereo", inputs=stereo_inputs)  # as read before the run: an edit meanwhile is a change
        prog.stop()
    result.previews_path = previews if config.stereo.previews or previews.is_dir() else None
    if config.stop_after == "stereo":
        return

    # fusion and mesh follow what they read: a cloud fused from other maps (a `colmap-pvs stereo` run on
    # dense/ since, say) is fused again, and a mesh of another cloud is meshed again
    inputs = fusion_inputs_sha256(dense)
    fused_from = prog.recorded("fusion", "inputs")
    if "fusion" not in prog.overwrite and cloud_pair_is_complete(fused) and fused_from == inputs:
        prog.skip("fusion", f"{fused} exists")
    else:
        if "fusion" not in prog.overwrite and cloud_pair_is_complete(fused):
            logger.info("reconstruct: the depth maps, images or model in %s changed since %s was fused "
                        "(or it has no record of them): fusing again", dense, fused)
        prog.start("fusion")
        _remove_stale(meshed)
        prog.unmark("mesh")
        fuse(FuseConfig(workspace_path=dense, output_path=fused, method=config.fusion_method))
        prog.mark("fusion", inputs=inputs)
        prog.stop()
    result.fused_path = fused
    result.num_fused_points = len(read_point_cloud(fused))
    if config.stop_after == "fusion":
        return

    if config.mesh:
        cloud = files_state_sha256([fused])
        if meshed.is_file() and "mesh" not in prog.overwrite and prog.recorded("mesh", "inputs") == cloud:
            prog.skip("mesh", f"{meshed} exists")
        elif result.num_fused_points < 4:
            logger.warning("reconstruct: the fused cloud has %d points; no mesh", result.num_fused_points)
        else:
            prog.start("mesh")
            mesh(
                MeshConfig(
                    input_path=fused,
                    output_path=meshed,
                    depth=config.mesh_depth,
                    num_threads=config.num_threads,
                )
            )
            prog.mark("mesh", inputs=cloud)
            prog.stop()
        result.mesh_path = meshed if meshed.is_file() else None
    logger.info(
        "reconstruct: finished in %.1f s: %d/%d images registered, %d sparse points, %d fused points",
        time.perf_counter() - total,
        result.num_registered,
        len(names),
        result.num_points3D,
        result.num_fused_points,
    )

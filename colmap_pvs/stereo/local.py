"""The local backend of ``stereo``: every pass of every reference in this process.

Python users (and the Ray backend) use :func:`~colmap_pvs.stereo.context.prepare_stereo` once, then
:func:`process_reference` per reference and pass.
"""

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from tqdm import tqdm

from ..config import config_json_bytes
from ..errors import ConfigError, WorkspaceError
from ..io.cleanup import remove_orphan_temps
from ..io.files import atomic_write_bytes
from ..io.workspace import write_fusion_cfg
from ..model import stored_config
from .config import CONFIG_FILENAME, Stage, StereoConfig
from .confirm import confirm_pass
from .context import (
    RefOutcome,
    StereoContext,
    StereoResult,
    patch_match_note,
    prepare_stereo,
    reference_threads,
)
from .filled import filled_pass
from .geometric import geometric_pass
from .outputs import pass_summary, remove_filled
from .photometric import photometric_pass
from .timing import Timer, sum_steps

logger = logging.getLogger(__name__)


def process_reference(ctx: StereoContext, name: str, stage: Stage) -> RefOutcome:
    """Compute (if not current) and atomically write one reference's maps for one pass.

    The pass's depth map is written last (after its provenance), so its existence with matching
    provenance marks the reference done. The geometric pass reads the photometric maps of ``name``
    and of its sources. With background writes (``prepare_stereo(background_io=True)``) the files
    appear after :meth:`StereoContext.flush`; ``timings`` then fills in ``writes`` at that point.
    """
    if stage == "photometric":
        return photometric_pass(ctx, name)
    if stage == "geometric":
        return geometric_pass(ctx, name)
    if stage == "filled":
        return filled_pass(ctx, name)
    if stage == "confirm":
        return confirm_pass(ctx, name)
    raise ConfigError(f"stage must be 'photometric', 'geometric', 'filled' or 'confirm', got {stage!r}")


def auxiliary_references(ctx: StereoContext) -> list[str]:
    """Sources of the references that are not references themselves (``patch-match.cfg`` lists a
    subset): the geometric pass needs their photometric maps, so they get a photometric pass too
    (with automatic sources), but no geometric maps and no ``fusion.cfg`` entry."""
    refs = set(ctx.references)
    extra: dict[str, None] = {}
    for name in ctx.references:
        sources, _ = ctx.sources_of(name)
        for s in sources or ():
            if s not in refs:
                extra[s] = None
    return sorted(extra)


_PASS_LABELS = {"geometric": ("stereo (geometric)", "geometric pass"),
                "filled": ("stereo (dense completion)", "dense completion"),
                "confirm": ("stereo (confirmed completion)", "confirmed completion")}


def _run_later_pass(ctx: StereoContext, names: list[str], stage: Stage, result: StereoResult,
                    outcomes: list[RefOutcome], skip: set[str]) -> None:
    """Run the geometric or the completion pass over ``names`` (but ``skip``), filling
    ``result.{stage}_processed / _done / _skipped`` and ``result.pass_seconds[stage]``."""
    timer = Timer()
    desc, label = _PASS_LABELS[stage]
    processed, done, skipped = (getattr(result, f"{stage}_{k}") for k in ("processed", "done", "skipped"))
    if stage in ("filled", "confirm"):  # never keep a completion of maps this run did not make
        for name in names:
            if name in skip:
                remove_filled(ctx.reference(name))
    todo = [name for name in names if name not in skip]
    workers = reference_threads(ctx.config, stage)
    with ThreadPoolExecutor(workers, thread_name_prefix=f"stereo-{stage}") as pool:
        run = pool.map(lambda name: process_reference(ctx, name, stage), todo) if workers > 1 else (
            process_reference(ctx, name, stage) for name in todo)
        # in the references' order, as each is done; an error stops the pass (map cancels what is queued)
        for name, out in zip(todo, tqdm(run, total=len(todo), desc=desc, unit="image"), strict=True):
            outcomes.append(out)
            if out.status == "done":
                done.append(name)
            elif out.status == "skipped":
                logger.warning("%s: skipping %s: %s", label, name, out.reason)
                skipped[name] = out.reason
            else:
                processed.append(name)
    ctx.flush()
    result.pass_seconds[stage] = timer.elapsed()
    logger.info("stereo %s", pass_summary(stage, outcomes))


def final_kind(config: StereoConfig) -> Stage:
    return "geometric" if config.geometric.enabled else "photometric"


def run_local(config: StereoConfig, weights: Path | None = None) -> StereoResult:
    """:func:`run_stereo` in this process."""
    wall = Timer()
    with wall.step("prepare"):
        ctx = prepare_stereo(config, background_io=True, weights=weights)
        ws = ctx.workspace
        remove_orphan_temps(ws.stereo_dir, recursive=True)  # what a killed run left behind
    atomic_write_bytes(ws.stereo_dir / CONFIG_FILENAME, config_json_bytes(
        config, checkpoint_used=str(ctx.checkpoint_path), checkpoint_sha256=ctx.checkpoint_sha256,
        model_config=stored_config(ctx.net.config)))
    result = StereoResult(workspace=ws)
    result.timings["prepare"] = wall.steps["prepare"]
    outcomes: list[RefOutcome] = []
    names = list(ctx.references)
    note = patch_match_note(ws, ctx.references, config.photometric.num_views)
    if note is not None:
        logger.warning("stereo: %s", note)
    result.auxiliary = auxiliary_references(ctx) if config.geometric.enabled else []
    work = names + result.auxiliary
    try:
        timer = Timer()
        bar = tqdm(work, desc="stereo (photometric)", unit="image")
        for i, name in enumerate(bar):
            if i + 1 < len(work):
                ctx.prefetch(work[i + 1])
            out = process_reference(ctx, name, "photometric")
            outcomes.append(out)
            if i >= len(names):  # an auxiliary source: reported in result.auxiliary only
                if out.status == "skipped":
                    logger.warning("no photometric maps for source %s: %s", name, out.reason)
                continue
            if out.status == "done":
                result.already_done.append(name)
            elif out.status == "skipped":
                logger.warning("skipping %s: %s", name, out.reason)
                result.skipped[name] = out.reason
            else:
                result.processed.append(name)
                bar.set_postfix(s=f"{out.seconds:.2f}")
            sources, _ = ctx.sources_of(name)
            if sources is not None:
                result.sources[name] = sources
        ctx.flush()
        result.pass_seconds["photometric"] = timer.elapsed()
        logger.info("stereo %s", pass_summary("photometric", outcomes))
        if config.geometric.enabled:
            _run_later_pass(ctx, names, "geometric", result, outcomes, set(result.skipped))
        if config.geometric.enabled and config.completion.enabled:
            _run_later_pass(ctx, names, "filled", result, outcomes,
                            set(result.skipped) | set(result.geometric_skipped))
            _run_later_pass(ctx, names, "confirm", result, outcomes,
                            set(result.skipped) | set(result.geometric_skipped) | set(result.filled_skipped))
        else:  # never keep a completion that no longer matches the maps
            for name in names:
                remove_filled(ctx.reference(name))
    finally:
        ctx.close()
    sum_steps(outcomes, into=result.timings)
    kind = final_kind(config)
    done = [n for n in names
            if ws.depth_map_path(n, kind).is_file() and ws.normal_map_path(n, kind).is_file()]
    if not done:  # an error, and the previous fusion.cfg is kept (not emptied)
        reasons = "; ".join(f"{n}: {r}" for n, r in list(result.skipped.items())[:3])
        raise WorkspaceError(
            f"no {kind} depth map in {str(ws.stereo_dir)!r}: all {len(names)} reference(s) were skipped "
            f"({reasons})"
        )
    write_fusion_cfg(ws.fusion_cfg, done)
    computed = len(set(result.processed) | set(result.geometric_processed) | set(result.filled_processed))
    total = wall.elapsed()
    result.pass_seconds["total"] = total
    result.seconds_per_image = total / computed if computed else 0.0
    logger.info("stereo: finished in %.1f s, %.2f s per computed image", total, result.seconds_per_image)
    return result

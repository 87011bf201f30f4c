"""The learned peers on ``hololens-dev`` with our cameras, references and sources: network maps only.

IterMVS (DTU and BlendedMVS weights) and PatchmatchNet, run by ``tools/teacher_labels.py``'s
:class:`Teacher` (their clones stay outside the repository; see that tool's docstring), on the
references and sources of ``hololens_quick.py`` (the same cached COLMAP model, the first ``N - 1`` of
each reference's ranked sources, the same depth ranges), at the images' own size (hololens-dev's
540 x 360, which is also ``hololens_quick.py``'s map size), scored by the same
:func:`colmap_pvs.evaluate.evaluate_depth`. Each peer's depth is written as the photometric map of its
own workspace ``WORK/quick/peer_<teacher>_n<N>_o<offset>``, and its own confidence (IterMVS: the
probability of its final estimate; PatchmatchNet: its photometric confidence) as that map's confidence,
so its numbers, relative AUSE included (how well the confidence ranks the AbsRel of the pixels), read like
ours::

    python benchmarks/peers.py --itermvs /path/IterMVS --patchmatchnet /path/PatchmatchNet \\
        --stride 3 --num_views 11
    python benchmarks/hololens_quick.py --stride 3 --num_views 11 --tag n11 \\
        --stereo geom_consistency=false geom_fill=false   # ours, the same references and sources

A rerun keeps a map only where its record (``stereo/provenance/NAME.peer.json``: teacher, weights,
sources, depth range, cameras and image size) is unchanged. The seconds printed are the mean forward
time of the maps computed now, the first (warm-up) one left out.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import sys
from pathlib import Path
from time import perf_counter

import numpy as np
import real_depth as rd
import torch
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
import teacher_labels as tl  # noqa: E402

from colmap_pvs.config import config_from_dict  # noqa: E402
from colmap_pvs.evaluate import EvaluateDepthConfig, evaluate_depth  # noqa: E402
from colmap_pvs.io.maps import write_array, write_depth_map  # noqa: E402
from colmap_pvs.io.workspace import write_patch_match_cfg  # noqa: E402
from colmap_pvs.views import ViewSelectionConfig  # noqa: E402


def record_of(teacher: tl.Teacher, sd: tl.SceneData, ref: str, sources: list[str], image) -> str:
    """What a map depends on, as a string: the teacher's cache key plus the views' cameras and size."""
    views = [ref, *sources]
    cams = np.concatenate([np.ravel(sd.Ks[n]) for n in views] + [np.ravel(sd.poses[n]) for n in views])
    depth_range = sd.selection.references[ref].depth_range
    meta = json.loads(tl.estimate_meta(teacher.key, teacher, ref, sources, depth_range))
    meta["cameras_sha256"] = hashlib.sha256(cams.astype(np.float64).tobytes()).hexdigest()
    meta["image_size"] = list(image.shape[:2])
    return json.dumps(meta, sort_keys=True)


def stored_record(path: Path) -> str | None:
    """The record a map was made with, or ``None`` (no record, or one that cannot be read)."""
    try:
        return json.dumps(json.loads(path.read_text())["record"], sort_keys=True)
    except (OSError, ValueError, KeyError, TypeError):
        return None


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    tl.add_clone_args(p)
    kinds = sorted(tl.TEACHER_KINDS)
    p.add_argument("--teachers", nargs="*", default=kinds, choices=kinds)
    rd.add_frame_args(p, stride=9)
    a = p.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    prepared = rd.quick_model(a)
    if prepared is None:
        return 2
    work, sparse = prepared
    torch.set_num_threads(a.threads)
    teachers = tl.load_teachers(a.teachers, tl.clones(a))
    for key, teacher in teachers.items():
        ws = rd.make_workspace(work / "quick" / f"peer_{key}_n{a.num_views}_o{a.offset}", a.data / "images",
                               sparse, keep_stereo=True)
        sd = tl.load_scene(ws, 1, config_from_dict(ViewSelectionConfig, {"num_views": a.num_views}))
        sources = rd.quick_sources(list(sd.Ks), sd.selection, a)
        write_patch_match_cfg(ws / "stereo" / "patch-match.cfg", sources)
        (ws / "stereo" / "provenance").mkdir(parents=True, exist_ok=True)
        images = tl.ImageCache(ws)
        seconds = []
        for ref, srcs in tqdm(sources.items(), desc=f"{key} N={a.num_views}", unit="image"):
            views = [ref, *srcs]
            record = record_of(teacher, sd, ref, srcs, images.get(ref))
            out = ws / "stereo" / "depth_maps" / f"{ref}.photometric.bin"
            conf_out = ws / "stereo" / "confidence_maps" / f"{ref}.photometric.bin"
            stamp = ws / "stereo" / "provenance" / f"{ref}.peer.json"
            if out.is_file() and conf_out.is_file() and stored_record(stamp) == record:
                continue
            stamp.unlink(missing_ok=True)  # a map without its record is never kept
            t0 = perf_counter()
            depth, conf = teacher.run([images.get(n) for n in views], [sd.Ks[n] for n in views],
                                      [sd.poses[n] for n in views], *sd.selection.references[ref].depth_range)
            seconds.append(perf_counter() - t0)
            write_depth_map(out, depth)
            write_array(conf_out, np.asarray(conf, np.float32))
            tl.atomic_json(stamp, {"record": json.loads(record)})
        m = evaluate_depth(EvaluateDepthConfig(workspace_path=ws, gt=a.data / "depth", gt_scale=0.001,
                                               kind="photometric", images=tuple(sources),
                                               output_path=ws / "metrics.photometric.json"))
        s = m.pooled
        under = " / ".join(f"{s.rel_under_pct[t]:.1f}" for t in sorted(s.rel_under_pct))
        speed = f", {np.mean(seconds[1:] or seconds):.2f} s per image" if seconds else ""
        ause = f", relative AUSE {m.sparsification['relative_ause']:.3f}" if m.sparsification else ""
        print(f"{key} N={a.num_views} offset {a.offset}: {len(sources)} refs, "
              f"coverage {s.coverage_pct:.1f} %, MAE {s.mae * 1000:.0f} mm, AbsRel {s.absrel:.4f}, "
              f"% under {sorted(s.rel_under_pct)}: {under}{ause}{speed}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

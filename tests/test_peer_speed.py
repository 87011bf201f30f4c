"""``benchmarks/peer_speed.py``'s pure logic: the sources and depth ranges it gives IterMVS are those our
``stereo`` command uses; the table's paired ratios (the timed runs need the data and the clone)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from colmap_pvs.cli.main import main
from colmap_pvs.synthetic.workspace import SyntheticWorkspaceConfig, make_synthetic_workspace

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
if str(BENCHMARKS) not in sys.path:
    sys.path.insert(0, str(BENCHMARKS))

import peer_speed as ps  # noqa: E402  (benchmarks/ is no package: on sys.path above)


def test_planned_sources_and_ranges_are_what_the_stereo_command_records(tmp_path, tiny_checkpoint):
    ws = tmp_path / "ws"
    info = make_synthetic_workspace(ws, SyntheticWorkspaceConfig(seed=3, width=96, height=72, num_views=4))
    first, second = sorted(info["image_names"])[:2]
    # one entry below num_views - 1: patch-match.cfg, not --num_views, decides its sources
    (ws / "stereo" / "patch-match.cfg").write_text(f"{first}\n__auto__, 1\n{second}\n__auto__, 2\n")
    fields = {"workspace_path": str(ws), "max_image_size": 64, "num_views": 3, "threads": 1}
    plan = ps.plan_views({**fields, "checkpoint": str(tiny_checkpoint)})
    refs = plan["references"]
    assert list(refs) == [first, second]
    assert len(refs[first]["sources"]) == 1 and len(refs[second]["sources"]) == 2
    assert set(plan["views"]) == {first, second, *refs[first]["sources"], *refs[second]["sources"]}
    assert all(view["size"] == [64, 48] for view in plan["views"].values())

    command = ps.stereo_command(sys.executable, ws, fields)
    args = command[command.index("stereo"):]
    assert args[1:] == ["--workspace_path", str(ws), "--max_image_size", "64", "--num_views", "3",
                        "--threads", "1"]
    assert main([*args, "--checkpoint", str(tiny_checkpoint), "--min_confidence", "0"]) == 0
    recorded = ps.recorded_views(ws, refs)
    assert {n: r["sources"] for n, r in recorded.items()} == {n: r["sources"] for n, r in refs.items()}
    assert ps.plan_mismatches(plan, ws) == []

    other = {"references": {**refs, first: {**refs[first], "sources": refs[second]["sources"]},
                            second: {**refs[second], "depth_range": [1.0, 2.0]}}}
    found = ps.plan_mismatches(other, ws)
    assert len(found) == 2 and found[0].startswith(f"{first}: sources") and "depth range" in found[1]
    (ws / "stereo" / "provenance" / f"{first}.photometric.json").unlink()
    assert ps.plan_mismatches(plan, ws) == [f"{first}: no photometric provenance"]


def test_summary_takes_the_median_of_paired_ratios():
    def run(repeat, side, wall):
        return {"repeat": repeat, "side": side, "wall_s": wall, "cpu_s": wall, "peak_rss_mb": 100.0}

    runs = [run(0, "ours", 8.0), run(0, "itermvs", 10.0), run(1, "ours", 30.0), run(1, "itermvs", 20.0),
            run(2, "ours", 9.0), run(2, "itermvs", 12.0)]
    text = "\n".join(ps.summary(runs, ["ours"]))
    assert "| ours | 3 | 9.0 | 9.0 | 100 |" in text and "| itermvs | 3 | 12.0 |" in text
    # the median of 0.8, 1.5 and 0.75, not the ratio of the medians (9 / 12)
    assert "ours / IterMVS, median of 3 paired ratio(s): wall 0.80x, CPU 0.80x, peak RSS 1.00x" in text
    runs += [run(0, "itermvs+filter", 16.0), run(1, "itermvs+filter", 20.0)]  # each peer its own pairs
    text = "\n".join(ps.summary(runs, ["ours"], ("itermvs", "itermvs+filter")))
    assert "ours / IterMVS, median of 3 paired ratio(s): wall 0.80x" in text
    assert "ours / itermvs+filter, median of 2 paired ratio(s): wall 1.00x" in text  # 0.5 and 1.5


def test_ours_pairs(tmp_path):
    assert ps.parse_ours([]) == [("ours", sys.executable)]
    python = tmp_path / "python"
    python.write_text("")
    assert ps.parse_ours([f"old={python}", f"new={python}"]) == [("old", str(python)), ("new", str(python))]
    for bad in ("old", f"old={tmp_path / 'none'}", f"itermvs={python}"):
        with pytest.raises(SystemExit, match="--ours"):
            ps.parse_ours([bad])
    with pytest.raises(SystemExit, match="taken"):
        ps.parse_ours([f"a={python}", f"a={python}"])

"""The contract of the object a stereo pass reads and writes (``stereo/reference.py``) and of its timer
(``stereo/timing.py``): the files a pass leaves follow from the :class:`Reference` alone, and a pass
finds its inputs through the run's one :class:`Reference` per image."""

from __future__ import annotations

import ast
import dataclasses
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from colmap_pvs.io.maps import read_array, read_depth_map, read_normal_map
from colmap_pvs.io.workspace import Workspace
from colmap_pvs.stereo.context import RefOutcome, StereoContext
from colmap_pvs.stereo.outputs import fingerprint, write_pass
from colmap_pvs.stereo.reference import PassMaps, PassRecord, Reference
from colmap_pvs.stereo.timing import Timer, sum_steps


def _maps(h: int = 6, w: int = 8, sources: int = 2) -> PassMaps:
    rng = np.random.default_rng(0)
    depth = rng.uniform(1.0, 3.0, (h, w)).astype(np.float32)
    normals = np.tile(np.array([0.0, 0.0, -1.0], np.float32), (h, w, 1))
    return PassMaps(depth, rng.uniform(0, 1, (h, w)).astype(np.float32), normals,
                    visibility=rng.uniform(0, 1, (sources, 2, 2)).astype(np.float32),
                    seeds=np.where(depth > 2.0, depth, 0.0).astype(np.float32))


@pytest.mark.parametrize("stage", ["photometric", "geometric"])
def test_write_pass_writes_what_the_reference_holds(tmp_path, stage):
    ws = Workspace(tmp_path)
    maps = _maps()
    if stage == "photometric":  # each pass carries its own extras only
        maps = dataclasses.replace(maps, seeds=None)
    else:
        maps = dataclasses.replace(maps, visibility=None)
    record = PassRecord({"stage": stage, "v": 1}, {"image_size": [8, 6], "sources": ["b.png", "c.png"]},
                        seed_fingerprint="abc" if stage == "geometric" else None)
    ref = Reference.of(ws, "a.png", ("b.png", "c.png"), (1.0, 3.0))
    done = ref.with_pass(stage, maps, record)
    assert ref.stage is None and ref.maps is None and ref.record is None  # with_pass makes a new reference
    assert (done.stage, done.maps, done.record, done.paths) == (stage, maps, record, ref.paths)
    with pytest.raises(dataclasses.FrozenInstanceError):
        done.name = "b.png"
    timer = Timer()
    write_pass(done, previews=True, timer=timer)

    out = done.paths[stage]
    assert out.depth == ws.depth_map_path("a.png", stage)  # the workspace's own layout
    np.testing.assert_array_equal(read_depth_map(out.depth), maps.depth)
    np.testing.assert_array_equal(read_normal_map(out.normals), maps.normals)
    np.testing.assert_array_equal(read_array(out.confidence), maps.confidence)
    prov = json.loads(out.provenance.read_text())
    assert prov == {"fingerprint": fingerprint(record.settings), "settings": record.settings, **record.extra}
    assert out.preview.is_file() and set(timer.steps) == {"writes", "previews"}
    if stage == "photometric":
        assert read_array(done.paths.visibility).shape == (2, 2, 2)  # [h, w, S] on disk
        assert all(done.paths.visibility_preview("a.png", k, s).is_file() for k, s in enumerate(ref.sources))
        assert not done.paths.seeds.exists()
    else:
        np.testing.assert_array_equal(read_array(done.paths.seeds), maps.seeds)
        assert json.loads(done.paths.seed_provenance.read_text()) == {"fingerprint": "abc"}
        assert not done.paths.visibility.exists()


def test_timer_steps_and_their_sum_over_a_run():
    timer = Timer()
    with timer.step("network"):
        pass
    with pytest.raises(RuntimeError), timer.step("normals"):
        raise RuntimeError("out of memory")
    nested = Timer()
    with nested.step("network"):
        pass
    timer.add(nested, "reestimate_")
    assert set(timer.steps) == {"network", "reestimate_network"}  # a failed step records nothing
    assert timer.elapsed() >= sum(timer.steps.values())
    outcomes = [RefOutcome("a", "photometric", "computed", timings={"network": 1.0}),
                RefOutcome("b", "photometric", "computed", timings={"network": 2.0}),
                RefOutcome("a", "geometric", "computed", timings={"consistency": 0.5})]
    assert sum_steps(outcomes, into={"prepare": 3.0}) == {"prepare": 3.0, "network": 3.0,
                                                          "geometric.consistency": 0.5}


PASS_MODULES = ("photometric", "geometric", "filled", "confirm")


def _workspace_paths(source: str) -> list[str]:
    """The calls in ``source`` that derive a file from the workspace (``ws.X(...)``,
    ``ctx.workspace.X(...)``, ``helper(ws, ...)``) and the path helpers it imports (``*_path``)."""
    def is_ws(node) -> bool:
        return (isinstance(node, ast.Name) and node.id == "ws") or (
            isinstance(node, ast.Attribute) and node.attr == "workspace")
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Call) and (
                (isinstance(node.func, ast.Attribute) and is_ws(node.func.value))
                or any(is_ws(a) for a in [*node.args, *(k.value for k in node.keywords)])):
            found.append(f"line {node.lineno}: {ast.unparse(node)[:60]}")
        if isinstance(node, ast.ImportFrom):
            found += [f"line {node.lineno}: imports {a.name}" for a in node.names if a.name.endswith("_path")]
    return found


def test_passes_read_their_files_through_their_reference():
    """No pass builds a path from the workspace: each reads its inputs and its own outputs' provenance
    through ``ctx.reference(name)`` (the paths made once per image and run)."""
    root = Path(__file__).resolve().parents[1] / "colmap_pvs" / "stereo"
    found = {m: _workspace_paths((root / f"{m}.py").read_text()) for m in PASS_MODULES}
    assert found == {m: [] for m in PASS_MODULES}
    assert _workspace_paths("p = seed_map_path(ws, name)\nq = ctx.workspace.depth_map_path(name, 'filled')")


def test_the_context_makes_one_reference_per_image(tmp_path):
    """``StereoContext.reference``: made once per image (its paths, its view-selection depth range; none
    without an entry), shared by every pass and every reference that reads it as a source."""
    ws = Workspace(tmp_path)
    fake = SimpleNamespace(workspace=ws, reference_cache={}, selection=SimpleNamespace(
        references={"a.png": SimpleNamespace(depth_range=(1.0, 3.0))}))
    a = StereoContext.reference(fake, "a.png")
    assert StereoContext.reference(fake, "a.png") is a and a.depth_range == (1.0, 3.0)
    assert a.paths == Reference.of(ws, "a.png").paths and a.maps is None
    assert StereoContext.reference(fake, "b.png").depth_range is None
    assert set(fake.reference_cache) == {"a.png", "b.png"}
    prov = a.paths["geometric"].provenance
    assert a.provenance("geometric") is None and not a.has_maps("geometric")
    prov.parent.mkdir(parents=True)
    prov.write_text('{"fingerprint": "f"}')
    assert a.provenance("geometric") == {"fingerprint": "f"}

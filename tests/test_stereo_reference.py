"""The contract of the object a stereo pass writes (``stereo/reference.py``) and of its timer
(``stereo/timing.py``): the files a pass leaves follow from the :class:`Reference` alone."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from colmap_pvs.io.maps import read_array, read_depth_map, read_normal_map
from colmap_pvs.io.workspace import Workspace
from colmap_pvs.stereo.context import RefOutcome
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
    assert ref.maps == {} and ref.records == {}  # with_pass makes a new reference
    with pytest.raises(dataclasses.FrozenInstanceError):
        done.name = "b.png"
    timer = Timer()
    write_pass(done, stage, previews=True, timer=timer)

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

"""``stereo --backend ray``: a local 2-CPU Ray cluster started and stopped by the tests.

Pinned here: Ray maps are byte-identical to a local run with the same threads, a rerun resumes, a
worker killed with ``os.kill`` mid-task is replaced and its reference retried elsewhere (nothing
half-written left), bounded retries, a clear error when workers cannot read the workspace, and the
same backend for ``reconstruct``'s stereo step. The task graph and the temp-file cleanup are tested
without Ray.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from conftest import make_tiny_checkpoint
from scenes import reconstruct_config, stereo_config

from colmap_pvs.adapt import run_adapted_stereo
from colmap_pvs.cli.main import main
from colmap_pvs.errors import DistributedError
from colmap_pvs.io.workspace import read_fusion_cfg
from colmap_pvs.stereo import CONFIG_FILENAME, StereoConfig, run_stereo
from colmap_pvs.stereo.ray import TaskGraph, graph_sources, run_task_graph, stereo_passes

#: Ray's native threads outlive ray.shutdown(): these tests run in a child pytest (tests/conftest.py).
pytestmark = pytest.mark.own_process

#: No test of this module may run longer (SIGALRM): a hang fails instead of stalling CI, with room for a
#: loaded 2-core machine.
TEST_SECONDS = 300
#: Tests that may take longer: the killed-worker test starts its own Ray for each of its runs.
LONGER_SECONDS = {"test_ray_started_by_the_run_survives_a_worker_killed_mid_task": 600}


# --------------------------------------------------------------------------- without Ray


def test_task_graph_orders_passes_by_sources():
    refs = ["a", "b", "c", "d"]
    sources = {"a": ["b"], "b": ["a", "x"], "c": None, "d": ["c"]}  # x: not a reference; c: unknown
    graph = TaskGraph(refs, ("photometric", "geometric"), sources)
    assert len(graph.tasks) == 8 and graph.remaining == 8
    order = [graph.pop() for _ in range(4)]
    assert order == [(n, "photometric") for n in refs] and graph.pop() is None
    graph.finish(("a", "photometric"))
    assert graph.pop() is None  # geometric a needs photometric b too
    graph.finish(("b", "photometric"))
    assert {graph.pop(), graph.pop()} == {("a", "geometric"), ("b", "geometric")}
    graph.finish(("d", "photometric"))
    assert graph.pop() is None  # d needs c; c needs everything
    graph.finish(("c", "photometric"))
    ready = [graph.pop(), graph.pop()]
    assert sorted(ready) == [("c", "geometric"), ("d", "geometric")] and graph.pop() is None
    graph.requeue(("c", "geometric"))  # lost with its worker: first in line again
    assert graph.pop() == ("c", "geometric")
    def passes(**flags):
        return stereo_passes(stereo_config(workspace_path=Path("x"), **flags))

    assert passes(geom_consistency=True, geom_fill=False) == ("photometric", "geometric")
    assert passes(geom_consistency=False, geom_fill=True) == ("photometric",)
    assert passes() == ("photometric", "geometric", "filled", "confirm")


def test_task_graph_dense_completion_waits_for_every_geometric_map():
    """The completion of a reads the geometric maps of a's best views among all references (not only
    its network sources), so it waits for the geometric pass of every reference."""
    graph = TaskGraph(["a", "b", "c"], ("photometric", "geometric", "filled"), {"a": ["b"], "b": ["a"],
                                                                                "c": ["b"]})
    assert graph.remaining == 9
    for _ in range(3):
        graph.pop()
    for n in "abc":
        graph.finish((n, "photometric"))
    assert sorted(graph.pop() for _ in range(3)) == [(n, "geometric") for n in "abc"]
    graph.finish(("a", "geometric"))
    graph.finish(("b", "geometric"))
    assert graph.pop() is None  # a's completion waits for c's geometric maps too
    graph.finish(("c", "geometric"))
    assert sorted(graph.pop() for _ in range(3)) == [(n, "filled") for n in "abc"]


def test_task_graph_confirmation_waits_for_every_completion():
    """The confirmation of a checks a's completion against the completions of its best views among
    all references, so it waits for every completion."""
    graph = TaskGraph(["a", "b", "c"], ("photometric", "geometric", "filled", "confirm"),
                      {"a": ["b"], "b": ["a"], "c": ["b"]})
    assert graph.remaining == 12
    for stage in ("photometric", "geometric"):
        assert sorted(graph.pop() for _ in range(3)) == [(n, stage) for n in "abc"]
        for n in "abc":
            graph.finish((n, stage))
    assert sorted(graph.pop() for _ in range(3)) == [(n, "filled") for n in "abc"]
    graph.finish(("a", "filled"))
    graph.finish(("b", "filled"))
    assert graph.pop() is None
    graph.finish(("c", "filled"))
    assert sorted(graph.pop() for _ in range(3)) == [(n, "confirm") for n in "abc"]


def test_task_graph_waits_for_every_photometric_map_with_splatted_seeds():
    """With ``geom_splat_min_sources`` a geometric pass may make its sources' seeds from their own
    sources' photometric maps, so it waits for every photometric map; without, for its sources'."""
    sources = {"a": ["b"], "b": ["a"], "c": ["b"]}
    def splat(n):
        return stereo_config(workspace_path=Path("x"), geom_splat_min_sources=n)

    assert graph_sources(splat(0), sources) == sources
    waits_all = graph_sources(splat(3), sources)
    assert waits_all == {"a": None, "b": None, "c": None}
    graph = TaskGraph(["a", "b", "c"], ("photometric", "geometric"), waits_all)
    for _ in range(3):
        graph.pop()
    graph.finish(("a", "photometric"))
    graph.finish(("b", "photometric"))
    assert graph.pop() is None  # a's sources are done, but c's photometric maps are not
    graph.finish(("c", "photometric"))
    assert sorted(graph.pop() for _ in range(3)) == [(n, "geometric") for n in "abc"]
    # the Ray driver's graph, with the default settings: geometric tasks wait for every photometric map
    plan = {"references": ["a", "b", "c"], "sources": sources, "auxiliary": []}
    ray_graph = run_task_graph(stereo_config(workspace_path=Path("x")), ("photometric", "geometric"), plan)
    for _ in range(3):
        ray_graph.pop()
    ray_graph.finish(("a", "photometric"))
    ray_graph.finish(("b", "photometric"))
    assert ray_graph.pop() is None


def test_task_graph_auxiliary_images_get_the_first_pass_only():
    graph = TaskGraph(["a", "b"], ("photometric", "geometric"), {"a": ["s"], "b": ["a"]}, ["s"])
    assert graph.tasks == [("a", "photometric"), ("b", "photometric"), ("s", "photometric"),
                           ("a", "geometric"), ("b", "geometric")]
    for _ in range(3):
        graph.pop()
    graph.finish(("a", "photometric"))
    graph.finish(("b", "photometric"))
    assert graph.pop() == ("b", "geometric") and graph.pop() is None  # a waits for its source s
    graph.finish(("s", "photometric"))
    assert graph.pop() == ("a", "geometric")
    graph.finish(("a", "geometric"))
    graph.finish(("b", "geometric"))
    assert graph.remaining == 0


def test_ray_flags_in_stereo_and_reconstruct():
    stereo, rec = stereo_config(workspace_path=Path("x")), reconstruct_config(image_path=Path("i"),
                                                                            workspace_path=Path("w"))
    assert rec.stereo.backend == stereo.backend == "local" and rec.stereo.ray == stereo.ray
    rec = reconstruct_config(image_path=Path("i"), workspace_path=Path("w"), backend="ray", ray_workers=3)
    assert rec.stereo.backend == "ray" and rec.stereo.ray.workers == 3
    with pytest.raises(SystemExit):
        main(["stereo", "--workspace_path", "x", "--backend", "spark"])


# --------------------------------------------------------------------------- with a local Ray


@pytest.fixture(autouse=True)
def _deadline(request):
    """Fail (instead of hanging CI) when a test runs over TEST_SECONDS (or its LONGER_SECONDS)."""
    seconds = LONGER_SECONDS.get(request.node.originalname, TEST_SECONDS)

    def expire(signum, frame):
        raise TimeoutError(f"test ran over {seconds} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.alarm(seconds)
    yield
    signal.alarm(0)
    signal.signal(signal.SIGALRM, previous)


def _start_local_ray(ray) -> None:
    ray.init(address="local", num_cpus=2, object_store_memory=80 * 1024**2, include_dashboard=False,
             logging_level="warning")


@pytest.fixture(scope="module")
def ray_cluster():
    """A local Ray with 2 CPUs and a small object store for this module; always shut down."""
    ray = pytest.importorskip("ray", reason='Ray is not installed (pip install "colmap-pvs[ray]")')
    handlers = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT)}  # ray.init replaces them
    _start_local_ray(ray)
    try:
        yield ray
    finally:
        ray.shutdown()
        for sig, handler in handlers.items():
            signal.signal(sig, handler)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """An analytic workspace (8 views, no maps), a tiny checkpoint and the local run's maps."""
    from scenes import make_analytic_workspace

    base = tmp_path_factory.mktemp("ray")
    root = base / "ws"
    make_analytic_workspace(root, n_views=8, width=240, height=180, focal=220.0, write_maps=False)
    (root / "stereo" / "fusion.cfg").unlink(missing_ok=True)
    ckpt = make_tiny_checkpoint(base / "tiny.pt")
    local = base / "local"
    shutil.copytree(root, local)
    import torch

    threads = torch.get_num_threads()
    try:
        result = run_stereo(_config(local, ckpt, backend="local", threads=1))
    finally:
        torch.set_num_threads(threads)
    assert len(result.processed) == 8
    return {"root": root, "ckpt": ckpt, "local": local}


def _config(ws: Path, ckpt: Path, **kw) -> StereoConfig:
    base = dict(workspace_path=ws, checkpoint=ckpt, max_image_size=240, num_views=3, min_confidence=0.0,
                backend="ray", ray_workers=2, ray_worker_threads=1)
    return stereo_config(**{**base, **kw})


def _copy(scene, tmp_path) -> Path:
    ws = tmp_path / "ws"
    shutil.copytree(scene["root"], ws)
    return ws


def _assert_same_maps(ws: Path, local: Path) -> None:
    """Every ``.bin`` map under ``stereo/`` (depth, normal, confidence, ... of every pass) is
    byte-identical to the local run's, the same files exist, and no temporary file is left."""
    files = sorted(p.relative_to(local / "stereo") for p in (local / "stereo").rglob("*.bin"))
    assert len(list((local / "stereo" / "depth_maps").glob("*.geometric.bin"))) == 8
    assert sorted(p.relative_to(ws / "stereo") for p in (ws / "stereo").rglob("*.bin")) == files
    for rel in files:
        assert (ws / "stereo" / rel).read_bytes() == (local / "stereo" / rel).read_bytes(), rel
    assert read_fusion_cfg(ws / "stereo" / "fusion.cfg") == read_fusion_cfg(local / "stereo" / "fusion.cfg")
    assert not [p for p in (ws / "stereo").rglob("*") if p.name.endswith(".tmp")]


@pytest.fixture
def no_ray_in_this_process():
    """No Ray runs in this process during the test, whatever ran before: the module's cluster, if an
    earlier test started it, is shut down and started again afterwards (its tests read its address
    when they run)."""
    ray = pytest.importorskip("ray", reason='Ray is not installed (pip install "colmap-pvs[ray]")')
    running = ray.is_initialized()
    if running:
        ray.shutdown()
    yield ray
    if running and not ray.is_initialized():
        _start_local_ray(ray)


@pytest.fixture
def expected_worker_deaths(monkeypatch):
    """The deaths these tests cause on purpose, taken out of the output and returned as a list.

    Ray's driver prints each worker death (``(raylet) A worker died or was killed ... SYSTEM_ERROR``)
    straight to stdout from a thread, whatever ``log_to_driver`` says; in a passing run the expected
    message would look like a failure. Every other message still goes through. The users' runs keep it.
    """
    ray = pytest.importorskip("ray", reason='Ray is not installed (pip install "colmap-pvs[ray]")')
    worker = getattr(getattr(ray, "_private", None), "worker", None)
    if worker is None or not hasattr(worker, "print_to_stdstream"):
        pytest.skip("this Ray version prints worker deaths elsewhere")
    deaths: list[str] = []
    original = worker.print_to_stdstream

    def quiet(data, *args, **kwargs):
        lines = data.get("lines", []) if isinstance(data, dict) else []
        if data.get("pid") == "raylet" and any("A worker died or was killed" in line for line in lines):
            deaths.extend(lines)
            return None
        return original(data, *args, **kwargs)

    monkeypatch.setattr(worker, "print_to_stdstream", quiet)
    return deaths


def test_ray_started_by_the_run_survives_a_worker_killed_mid_task(no_ray_in_this_process, scene, tmp_path,
                                                                  expected_worker_deaths):
    """The default `--ray_address ""` starts a local Ray (and stops it, restoring this process's signal
    handlers); a worker killed with SIGKILL while it runs a task is replaced, its reference runs again
    elsewhere, and every map equals the local run's.

    A kill can land just after the worker's task returned (its title still says ``process``): that run
    rightly retries nothing, and another run on a fresh copy is made (at most 3 runs with a kill)."""
    ray = no_ray_in_this_process
    before = signal.getsignal(signal.SIGTERM)

    def after_run() -> None:
        assert not ray.is_initialized() and signal.getsignal(signal.SIGTERM) is before

    for attempt in range(3):
        (tmp_path / f"run{attempt}").mkdir()
        ws, killed, result, error = _run_killing_a_worker(scene, tmp_path / f"run{attempt}", after_run,
                                                           ray_address="")
        assert error is None, f"the lost reference was not retried: {error}"
        assert killed[0] not in _worker_pids("any")
        assert sorted(result.processed) == sorted(read_fusion_cfg(scene["local"] / "stereo" / "fusion.cfg"))
        _assert_same_maps(ws, scene["local"])
        if sum(result.retried.values()) >= 1:  # the lost reference ran again, elsewhere
            break
    assert sum(result.retried.values()) >= 1, "a worker was killed in 3 runs, but no task was retried"


def test_cli_driver_killed_then_rerun_resumes_with_local_maps(ray_cluster, scene, tmp_path):
    """`colmap-pvs stereo --backend ray` joins the cluster (HOST:PORT); its driver is killed mid-run;
    the rerun keeps the finished maps, computes the rest, and every map equals the local run's."""
    ws = _copy(scene, tmp_path)
    address = ray_cluster.get_runtime_context().gcs_address
    argv = [sys.executable, "-m", "colmap_pvs.cli", "stereo", "--workspace_path", str(ws), "--checkpoint",
            str(scene["ckpt"]), "--num_views", "3", "--max_image_size", "240", "--min_confidence", "0",
            "--backend", "ray", "--ray_address", address, "--ray_workers", "2", "--ray_worker_threads", "1"]
    driver = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    maps = ws / "stereo" / "depth_maps"
    try:
        while driver.poll() is None and not list(maps.glob("*.geometric.bin")):
            time.sleep(0.01)
        driver.kill()  # the driver dies mid-run; Ray then kills its workers
    finally:
        _, err = driver.communicate(timeout=30)
    assert driver.returncode == -signal.SIGKILL, err.decode()[-2000:]
    # a finished geometric pass (its provenance: the confirmation may still add to its maps)
    provenance = ws / "stereo" / "provenance"
    finished = {p.name: p.stat().st_mtime_ns for p in provenance.glob("*.geometric.json")
                if (maps / p.name.replace(".json", ".bin")).is_file()}
    assert finished
    saved = json.loads((ws / "stereo" / CONFIG_FILENAME).read_text())
    assert saved["config"]["backend"] == "ray" and saved["checkpoint_used"] == str(scene["ckpt"])
    result = run_stereo(_config(ws, scene["ckpt"], ray_workers=1))
    assert len(result.already_done) >= len(finished) and len(result.already_done) + len(result.processed) == 8
    assert result.retried == {}
    for name, mtime in finished.items():  # kept, not recomputed
        assert (provenance / name).stat().st_mtime_ns == mtime
    _assert_same_maps(ws, scene["local"])


def _started_by_this_process(pid: int) -> bool:
    """Whether ``pid`` descends from this process (the workers of a Ray this process started): other
    test runs on the same machine have Ray workers too, which are neither watched nor killed."""
    me = os.getpid()
    while pid > 1:
        try:
            stat = (Path("/proc") / str(pid) / "stat").read_text()
        except OSError:
            return False
        pid = int(stat.rpartition(")")[2].split()[1])  # the parent's pid (after the command's name)
        if pid == me:
            return True
    return False


def _worker_pids(state: str) -> list[int]:
    """PIDs of the Ray StereoWorker processes of this process's Ray; ``state="process"``: those running a
    task right now."""
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            title = (entry / "cmdline").read_bytes().split(b"\0")[0].decode(errors="replace")
        except OSError:
            continue
        if title.startswith("ray::StereoWorker") and (
            state == "any" or title.startswith(f"ray::StereoWorker.{state}")
        ) and _started_by_this_process(int(entry.name)):
            pids.append(int(entry.name))
    return pids


def _kill_busy_worker(killed: list[int], stop: threading.Event) -> None:
    """Kill the first worker seen running ``process`` (mid-task) with SIGKILL.

    Between scans of ``/proc`` (which can take longer than a whole task of the tiny network on a quiet
    machine) only the known workers' own process titles are watched, one small read each; the scan is
    repeated every 50 ms, so a worker left idle by an earlier run cannot hide the new run's worker.
    """
    while not stop.is_set():
        titles = {pid: Path("/proc") / str(pid) / "cmdline" for pid in _worker_pids("any")}
        rescan = time.monotonic() + 0.05
        while titles and not stop.is_set() and time.monotonic() < rescan:
            for pid, title in list(titles.items()):
                try:
                    busy = title.read_bytes().startswith(b"ray::StereoWorker.process")
                except OSError:  # that worker is gone
                    del titles[pid]
                    continue
                if busy:
                    os.kill(pid, signal.SIGKILL)
                    killed.append(pid)
                    return
            time.sleep(0.001)
        if not titles:
            time.sleep(0.005)


def _run_killing_a_worker(scene, tmp_path, after_run, **config):
    """``run_stereo`` on a fresh copy of the scene while :func:`_kill_busy_worker` watches; repeated (at
    most 3 runs) while the killer missed every short task of the tiny network. ``after_run()`` is
    called after each run. Returns ``(workspace, killed pids, result or None, DistributedError or None)``;
    a run that fails although nothing was killed fails the test."""
    for attempt in range(3):
        (tmp_path / f"try{attempt}").mkdir()
        ws = _copy(scene, tmp_path / f"try{attempt}")
        killed: list[int] = []
        stop = threading.Event()
        killer = threading.Thread(target=_kill_busy_worker, args=(killed, stop), daemon=True)
        killer.start()
        result = error = None
        try:
            result = run_stereo(_config(ws, scene["ckpt"], **config))
        except DistributedError as exc:
            error = exc
        finally:
            stop.set()
            killer.join(30)  # it checks `stop` every few ms
        if after_run is not None:
            after_run()
        if killed:
            break
        assert error is None, f"the run failed although no worker was killed: {error}"
    assert len(killed) == 1, "no worker was seen running a task in 3 runs"
    return ws, killed, result, error


def test_ray_retries_are_bounded(ray_cluster, scene, tmp_path, expected_worker_deaths):
    """With ``ray_max_retries=0`` the first worker lost stops the run with an error naming its reference.

    The tiny network's tasks are short, so the killer thread can miss every one of them; such a run
    then simply finishes. It is repeated on a fresh copy (at most 3 tries) until a worker was killed.
    """
    error = None
    # no retries allowed: the first worker lost stops the run, naming its reference. The kill can land
    # just after the worker's last task returned (its title still says ``process``); that run rightly
    # finishes, so up to 3 runs with a kill are made.
    for attempt in range(3):
        (tmp_path / f"run{attempt}").mkdir()
        ws, killed, _, error = _run_killing_a_worker(scene, tmp_path / f"run{attempt}", None,
                                                     ray_max_retries=0, ray_workers=1)
        if error is not None:
            break
    assert error is not None, "a worker was killed mid-task in 3 runs, but no run failed"
    assert re.search(r"view_\d+.png' \((photometric|geometric) pass\): its Ray worker died 1 time\(s\) "
                     r"\(last: ActorDiedError; ray_max_retries=0\)", str(error)), str(error)
    assert not [p for p in (ws / "stereo").rglob("*") if p.name.endswith(".tmp")]
    deadline = time.monotonic() + 60  # a wait, not a time limit: it ends when the workers are gone
    while _worker_pids("any") and time.monotonic() < deadline:  # the run kills its workers when it stops
        time.sleep(0.2)
    assert _worker_pids("any") == []


def test_ray_worker_cannot_read_workspace(ray_cluster, tmp_path, capsys):
    missing = tmp_path / "not-mounted"
    assert main(["stereo", "--workspace_path", str(missing), "--backend", "ray", "--ray_workers", "1"]) == 1
    err = capsys.readouterr().err
    assert f"Ray worker on {socket.gethostname()}" in err and str(missing) in err
    assert "every Ray node sees" in err and "Traceback" not in err


def test_ray_worker_that_fits_no_node_is_refused(ray_cluster, scene, tmp_path):
    ws = _copy(scene, tmp_path)
    with pytest.raises(DistributedError, match="no Ray node can hold one worker of ray_worker_threads=3"):
        run_stereo(_config(ws, scene["ckpt"], ray_worker_threads=3, ray_workers=1, ray_address=""))


def test_reconstruct_stereo_step_on_ray(ray_cluster, analytic_scene, tmp_path):
    from colmap_pvs.reconstruct import reconstruct

    src = analytic_scene["root"]
    config = reconstruct_config(image_path=src / "images", workspace_path=tmp_path / "out",
                               input_path=src / "sparse", checkpoint=make_tiny_checkpoint(tmp_path / "t.pt"),
                               num_views=3, stop_after="stereo", backend="ray", ray_workers=1)
    reconstruct(config)
    stereo = tmp_path / "out" / "dense" / "stereo"
    assert len(list((stereo / "depth_maps").glob("*.geometric.bin"))) == 5
    saved = json.loads((stereo / CONFIG_FILENAME).read_text())["config"]
    assert saved["backend"] == "ray" and saved["ray"]["workers"] == 1


def test_ray_writes_the_maps_of_sub_folder_names_where_colmap_does(ray_cluster, tmp_path):
    """Image names with sub-folders, spaces and non-ASCII letters on Ray workers: the same maps as a
    local run, at COLMAP's paths."""
    from scenes import ODD_NAMES, make_odd_names_workspace

    base = make_odd_names_workspace(tmp_path / "base")
    ckpt = make_tiny_checkpoint(tmp_path / "t.pt")
    for backend in ("local", "ray"):
        shutil.copytree(base, tmp_path / backend)
        res = run_stereo(stereo_config(workspace_path=tmp_path / backend, checkpoint=ckpt, num_views=3,
                                       max_image_size=64, geom_min_consistent=1, threads=1, backend=backend,
                                       ray_workers=2))
        assert sorted(res.processed) == sorted(ODD_NAMES)
    for name in ODD_NAMES:
        for kind in ("photometric", "geometric", "filled"):
            rel = Path("stereo") / "depth_maps" / f"{name}.{kind}.bin"
            assert (tmp_path / "ray" / rel).read_bytes() == (tmp_path / "local" / rel).read_bytes(), rel


def test_ray_adapts_once_then_matches_local(ray_cluster, analytic_scene, tmp_path):
    """With test-time adaptation the step above stereo adapts once, then every worker runs the adapted
    weights: the maps equal a local adapted run's."""
    import torch

    ckpt = make_tiny_checkpoint(tmp_path / "base.pt", channels_last=False)
    runs = {}
    for backend in ("local", "ray"):
        ws = tmp_path / backend
        shutil.copytree(analytic_scene["root"], ws)
        for sub in ("depth_maps", "normal_maps"):
            shutil.rmtree(ws / "stereo" / sub)
        threads = torch.get_num_threads()
        try:
            runs[backend] = run_adapted_stereo(stereo_config(
                workspace_path=ws, checkpoint=ckpt, num_views=3, max_image_size=160, min_confidence=0.0,
                adapt_steps=2, threads=1, backend=backend, ray_workers=2, ray_worker_threads=1))
        finally:
            torch.set_num_threads(threads)
    assert runs["local"].adapt_seconds > 0 and runs["ray"].adapt_seconds > 0
    assert len(runs["ray"].processed) == 5
    assert (tmp_path / "ray" / "stereo" / "adapt" / "adapted.pt").is_file()
    for f in sorted((tmp_path / "local" / "stereo" / "depth_maps").glob("*.bin")):
        assert (tmp_path / "ray" / "stereo" / "depth_maps" / f.name).read_bytes() == f.read_bytes(), f.name


def test_ray_geometric_reestimate_matches_the_local_run(ray_cluster, scene, tmp_path):
    """``geom_reestimate`` (a network run inside the geometric pass) on Ray workers: the same maps as a
    local run of it, resumed from the photometric maps of the local run without the re-estimate."""
    import torch

    local = tmp_path / "local"
    shutil.copytree(scene["local"], local)
    threads = torch.get_num_threads()
    try:
        res = run_stereo(_config(local, scene["ckpt"], backend="local", threads=1, geom_reestimate=True))
    finally:
        torch.set_num_threads(threads)
    assert res.processed == [] and len(res.geometric_processed) == 8
    assert "geometric.reestimate_network" in res.timings
    ws = tmp_path / "ws"
    shutil.copytree(scene["local"], ws)
    result = run_stereo(_config(ws, scene["ckpt"], geom_reestimate=True))
    assert len(result.already_done) == 8 and result.retried == {}
    _assert_same_maps(ws, local)
    prov = json.loads((ws / "stereo" / "provenance" / f"{sorted(result.already_done)[0]}.geometric.json")
                      .read_text())
    assert prov["reestimated"] is True

"""Scale-out of the ``stereo`` step on Ray: one task per reference image and pass, on worker actors.

``StereoConfig(backend="ray")`` (``colmap-pvs stereo --backend ray``) runs
:func:`run_stereo_ray` instead of the local loop. The driver (this process)

1. starts a local Ray (``ray_address=""``) or joins a cluster (``auto`` or ``HOST:PORT``);
2. starts ``ray_workers`` actors of ``ray_worker_threads`` CPUs each. Every actor checks that it can
   read the workspace, then calls :func:`~colmap_pvs.stereo.context.prepare_stereo` once (sparse model,
   view selection and checkpoint loaded once per actor, never per task);
3. hands out one task per reference and pass (photometric, then geometric when
   ``geom_consistency`` is true, then the dense completion when ``geom_fill`` is true too). A
   geometric task of reference R is handed out only after the photometric tasks of R
   and of R's sources finished, a completion task after every geometric task. Each task is
   :func:`~colmap_pvs.stereo.local.process_reference`, which writes the maps atomically straight into the
   shared workspace, exactly as the local backend does: only names and small outcome records travel
   through Ray's object store;
4. survives the loss of a worker: a task whose actor died (killed, out of memory, node lost, or over
   ``ray_task_timeout``) goes back to the queue and runs on another actor; a replacement actor is
   started; a reference whose workers died more than ``ray_max_retries`` times stops the run with a
   :class:`~colmap_pvs.errors.DistributedError`. Temporary files a killed worker left behind are removed
   (:func:`colmap_pvs.io.cleanup.remove_orphan_temps`; all of them once every worker is gone);
5. writes ``stereo/fusion.cfg`` and the resolved config, like the local backend.

A rerun resumes like a local one: finished references come back as ``done`` from the workers.
Inputs (workspace, and ``--checkpoint`` if given) must live at the same path on a file system every node
sees. Ray is imported only here, and only when the Ray backend runs (``pip install "colmap-pvs[ray]"``).
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

from tqdm import tqdm

from .. import __version__
from ..config import config_json_bytes, replace_config
from ..errors import CheckpointError, ColmapPVSError, DistributedError, WorkspaceError
from ..io.cleanup import remove_orphan_temps
from ..io.files import atomic_write_bytes
from ..io.workspace import Workspace, write_fusion_cfg
from ..model import stored_config
from ..openmp import wait_env
from ..views import reference_sources
from .config import CONFIG_FILENAME, StereoConfig
from .context import RefOutcome, StereoResult, patch_match_note, prepare_stereo
from .local import auxiliary_references, process_reference
from .outputs import pass_summary, remove_filled
from .reference import Reference
from .timing import Timer, sum_steps

logger = logging.getLogger(__name__)

#: Object store of a Ray started by the driver: only names and outcome records travel through it.
LOCAL_OBJECT_STORE_BYTES = 128 * 1024**2
#: Seconds between two checks of the running tasks (timeouts, interrupts).
POLL_SECONDS = 0.5
SHARED_FS_HINT = (
    "with --backend ray the workspace (and --checkpoint) must be on a file system every Ray node "
    "sees, at the same path (NFS, a cluster file system, or a one-machine cluster)"
)

Task = tuple[str, str]  # (reference name, pass)


def stereo_passes(config: StereoConfig) -> tuple[str, ...]:
    """The passes of a stereo run, in order: photometric, then geometric if the config asks for it,
    then the geometric maps' dense completion (``filled``) if it asks for that too."""
    if not config.geometric.enabled:
        return ("photometric",)
    return ("photometric", "geometric", "filled", "confirm") if config.completion.enabled else (
        "photometric", "geometric")


def graph_sources(config: StereoConfig, sources: dict[str, list[str] | None]) -> dict[str, list[str] | None]:
    """The sources the geometric task of each reference waits for (:class:`TaskGraph`): its network
    sources, or every image (``None``) when ``geom_splat_min_sources`` is on: that pass may make the
    seeds of its sources from *their* sources' photometric maps (``docs/CONVENTIONS.md``)."""
    if config.geometric.splat_min_sources > 0:
        return dict.fromkeys(sources)
    return dict(sources)


def run_task_graph(config: StereoConfig, passes: tuple[str, ...], plan: dict) -> TaskGraph:
    """The task graph of a Ray run from the driver's ``plan`` (its ``references``, their network
    ``sources`` and the ``auxiliary`` images that only get the first pass), waiting as
    :func:`graph_sources` says."""
    return TaskGraph(plan["references"], passes, graph_sources(config, plan["sources"]), plan["auxiliary"])


@dataclass
class DistributedStereoResult(StereoResult):
    """:class:`~colmap_pvs.stereo.StereoResult` plus what the cluster did.

    Attributes:
        workers: actors that did work; nodes: their host names.
        retried: ``"NAME/PASS"`` -> how many times its worker died under it (it then ran elsewhere).
        wall_seconds: wall time of the whole run (workers starting included); ``seconds_per_image`` is
            that per computed reference, ``seconds_per_task`` the mean compute time of one task on
            one worker.
    """

    workers: int = 0
    seconds_per_task: float = 0.0
    nodes: list[str] = field(default_factory=list)
    retried: dict[str, int] = field(default_factory=dict)
    wall_seconds: float = 0.0


# --------------------------------------------------------------------------- the task graph


class TaskGraph:
    """Tasks ``(image, pass)`` and their order: the second pass of reference R waits for the first pass
    of R and of R's sources (``None``: for every image); a third pass (the dense completion, which
    reads the geometric maps of R's best views by score among the references) waits for the second
    pass of every reference, and a fourth (its confirmation, which reads their completions) for the
    third pass of every reference. ``auxiliary`` images (sources that are not references) get the
    first pass only."""

    def __init__(self, references: list[str], passes: tuple[str, ...], sources: dict[str, list[str] | None],
                 auxiliary: list[str] = ()):
        first = [*references, *auxiliary]
        self.tasks: list[Task] = [(name, passes[0]) for name in first]
        self.tasks += [(name, stage) for stage in passes[1:] for name in references]
        self._waiting: dict[Task, set[Task]] = {}
        self._dependents: dict[Task, list[Task]] = {t: [] for t in self.tasks}
        self._ready: deque[Task] = deque()
        self.finished: set[Task] = set()
        self._ready.extend((name, passes[0]) for name in first)
        for i, stage in enumerate(passes):
            for name in references if i else ():
                task = (name, stage)
                pool = first if i == 1 else references  # the images the previous pass ran on
                srcs = sources.get(name)
                needed = set(pool) & ({name, *srcs} if srcs is not None and i == 1 else set(pool))
                self._waiting[task] = {(s, passes[i - 1]) for s in needed}
                for dep in self._waiting[task]:
                    self._dependents[dep].append(task)

    @property
    def remaining(self) -> int:
        return len(self.tasks) - len(self.finished)

    def pop(self) -> Task | None:
        """The next task whose inputs exist, or ``None``."""
        return self._ready.popleft() if self._ready else None

    def requeue(self, task: Task) -> None:
        """Put a task that was lost with its worker back at the front of the queue."""
        self._ready.appendleft(task)

    def finish(self, task: Task) -> None:
        self.finished.add(task)
        for dep in self._dependents[task]:
            waiting = self._waiting[dep]
            waiting.discard(task)
            if not waiting:
                del self._waiting[dep]
                self._ready.append(dep)


# --------------------------------------------------------------------------- the worker (a Ray actor)


def check_workspace_access(config: StereoConfig, weights: Path | None = None) -> None:
    """Fail with a message naming this host when it cannot read the inputs or write ``stereo/``."""
    where = f"Ray worker on {socket.gethostname()} (pid {os.getpid()})"
    root = Path(config.workspace_path)
    if not root.is_dir():
        raise WorkspaceError(
            f"{where} cannot read the workspace {str(root)!r}: no such folder; {SHARED_FS_HINT}"
        )
    for sub in ("images", "sparse"):
        path = root / sub
        if not path.is_dir() or not os.access(path, os.R_OK | os.X_OK):
            raise WorkspaceError(
                f"{where} cannot read {str(path)!r} (missing or unreadable); {SHARED_FS_HINT}"
            )
    stereo = root / "stereo"
    try:
        stereo.mkdir(exist_ok=True)
    except OSError as exc:
        raise WorkspaceError(f"{where} cannot create {str(stereo)!r} ({exc}); {SHARED_FS_HINT}") from None
    if not os.access(stereo, os.W_OK | os.X_OK):
        raise WorkspaceError(f"{where} cannot write into {str(stereo)!r}; {SHARED_FS_HINT}")
    for path in (config.checkpoint, weights):
        if path is not None and not os.access(path, os.R_OK):
            raise CheckpointError(f"{where} cannot read the checkpoint {str(path)!r}; {SHARED_FS_HINT}")


class StereoWorker:
    """One Ray actor: the stereo context is prepared once, then references are processed one by one."""

    def __init__(self, config: StereoConfig, weights: Path | None = None):
        self.config = config
        self.weights = weights
        self.ctx = None

    def setup(self, passes: tuple[str, ...]) -> dict:
        """Check the workspace, :func:`prepare_stereo`, and return who we are plus the reference plan."""
        timer = Timer()
        check_workspace_access(self.config, self.weights)
        self.ctx = ctx = prepare_stereo(self.config, weights=self.weights)
        sources: dict[str, list[str] | None] = {}
        for name, spec in ctx.references.items():
            try:
                count = ctx.config.photometric.num_views - 1
                sources[name] = list(reference_sources(ctx.selection, name, spec, count))
            except (ColmapPVSError, KeyError, ValueError):
                sources[name] = None  # unknown: a later pass waits for every map of the previous one
        return {
            "host": socket.gethostname(),
            "pid": os.getpid(),
            "version": __version__,
            "seconds": timer.elapsed(),
            "references": list(ctx.references),
            "sources": sources,
            # Sources that are not references get the first pass too when a later pass reads them.
            "auxiliary": list(auxiliary_references(ctx)) if len(passes) > 1 else [],
            "checkpoint": str(ctx.checkpoint_path),
            "checkpoint_sha256": ctx.checkpoint_sha256,
            "model_config": stored_config(ctx.net.config),
            "patch_match_note": patch_match_note(ctx.workspace, ctx.references,
                                                 ctx.config.photometric.num_views),
        }

    def process(self, name: str, stage: str):
        """:func:`~colmap_pvs.stereo.local.process_reference` for one reference and pass."""
        return process_reference(self.ctx, name, stage)


# --------------------------------------------------------------------------- the driver


def _import_ray():
    try:
        import ray
    except ImportError:
        raise DistributedError('--backend ray needs Ray: pip install "colmap-pvs[ray]"') from None
    return ray


def worker_config(config: StereoConfig) -> StereoConfig:
    """The config the workers run: absolute paths (workers have their own working folder), the local
    per-reference code path and ``ray_worker_threads`` torch threads."""
    changes: dict = {
        "backend": "local",
        "threads": config.ray.worker_threads,
        "workspace_path": Path(config.workspace_path).expanduser().absolute(),
    }
    if config.checkpoint is not None:
        changes["checkpoint"] = Path(config.checkpoint).expanduser().absolute()
    return replace_config(config, **changes)


def _connect(ray, config: StereoConfig) -> bool:
    """Start or join Ray; True when this call started it (and so must shut it down)."""
    if ray.is_initialized():
        return False
    if config.ray.address:
        logger.info("stereo: joining the Ray cluster at %s", config.ray.address)
        ray.init(address=config.ray.address, log_to_driver=True, logging_level=logging.WARNING)
    else:
        cpus = (config.ray.workers * config.ray.worker_threads) if config.ray.workers else os.cpu_count() or 1
        logger.info("stereo: starting a local Ray with %d CPU(s)", cpus)
        ray.init(address="local", num_cpus=cpus, object_store_memory=LOCAL_OBJECT_STORE_BYTES,
                 include_dashboard=False, log_to_driver=True, logging_level=logging.WARNING)
    return True


_SIGNALS = ("SIGTERM", "SIGINT")


def _signal_handlers() -> dict:
    """This process's handlers of SIGTERM and SIGINT (``ray.init`` replaces them)."""
    return {name: signal.getsignal(getattr(signal, name)) for name in _SIGNALS if hasattr(signal, name)}


def _restore_signal_handlers(handlers: dict) -> None:
    if threading.current_thread() is not threading.main_thread():
        return  # only the main thread may set handlers (and only it had them replaced)
    for name, handler in handlers.items():
        if handler is not None:
            signal.signal(getattr(signal, name), handler)


def _reraise(exc: BaseException):
    """Raise the exception a worker raised (Ray wraps it in a ``RayTaskError``): our own errors as
    they are (a clean message), anything else chained to Ray's error (which holds the remote traceback)."""
    cause = getattr(exc, "cause", None)
    if isinstance(cause, ColmapPVSError):
        raise cause from None
    if isinstance(cause, BaseException):
        raise cause from exc
    raise exc


class _Driver:
    def __init__(self, ray, config: StereoConfig, passes: tuple[str, ...], joined: bool,
                 weights: Path | None = None):
        from ray import exceptions as rex

        self.ray, self.config, self.passes = ray, config, passes
        self.wcfg = worker_config(config)
        self.weights = None if weights is None else Path(weights).expanduser().absolute()
        self.deaths_types = (rex.RayActorError, rex.WorkerCrashedError, rex.NodeDiedError,
                             rex.OutOfMemoryError)
        self.task_error = rex.RayTaskError
        cpus = ray.cluster_resources().get("CPU", 0)
        self.num_workers = config.ray.workers or max(1, int(cpus // config.ray.worker_threads))
        if self.num_workers * config.ray.worker_threads > cpus:
            logger.warning("stereo: %d workers x %d threads need more CPUs than the cluster has (%g); "
                           "some workers wait", self.num_workers, config.ray.worker_threads, cpus)
        memory = int(config.ray.worker_memory * 2**30)
        self._check_fits(memory, joined)
        self.actor_cls = ray.remote(StereoWorker).options(
            num_cpus=config.ray.worker_threads, memory=memory or None, max_restarts=0, max_task_retries=0,
            runtime_env={"env_vars": wait_env(os.environ)},
        )
        self.deaths_left = self.num_workers * (config.ray.max_retries + 1)
        self.actors: list = []
        self.starting: dict = {}  # setup ref -> actor
        self.idle: deque = deque()
        self.running: dict = {}  # process ref -> (actor, task, start)
        self.timed_out: set = set()
        self.info: dict = {}  # actor id -> setup info
        self.plan: dict | None = None

    def _check_fits(self, memory: int, joined: bool) -> None:
        """Fail (or, joining a cluster an autoscaler may grow, warn) if no node can hold a worker."""
        nodes = [n.get("Resources", {}) for n in self.ray.nodes() if n.get("Alive")]
        need = {"CPU": self.config.ray.worker_threads, "memory": memory}
        if any(all(res.get(k, 0) >= v for k, v in need.items()) for res in nodes):
            return
        have = ", ".join(f"{r.get('CPU', 0):g} CPUs / {r.get('memory', 0) / 2**30:.1f} GiB" for r in nodes)
        msg = (f"no Ray node can hold one worker of ray_worker_threads={self.config.ray.worker_threads} CPUs "
               f"and ray_worker_memory={self.config.ray.worker_memory:g} GiB (nodes: {have or 'none'})")
        if not joined:
            raise DistributedError(msg)
        logger.warning("stereo: %s; waiting for the cluster to grow", msg)

    def spawn(self) -> None:
        actor = self.actor_cls.remote(self.wcfg, self.weights)
        self.actors.append(actor)
        self.starting[actor.setup.remote(self.passes)] = actor

    def kill_all(self) -> None:
        for actor in self.actors:
            try:
                self.ray.kill(actor, no_restart=True)
            except Exception as exc:  # best effort at shutdown
                logger.debug("could not kill a Ray worker: %s", exc)

    def _worker_name(self, actor) -> str:
        info = self.info.get(id(actor))
        return f"pid {info['pid']} on {info['host']}" if info else "a starting worker"

    def _lost(self, actor, what: str, exc: BaseException) -> None:
        """Account for a dead worker and start a replacement."""
        self.deaths_left -= 1
        if self.deaths_left < 0:
            raise DistributedError(f"Ray workers died too often (last: {what}: {exc}); giving up")
        try:
            self.ray.kill(actor, no_restart=True)
        except Exception:  # it is already gone
            pass
        self.spawn()

    def on_started(self, ref) -> None:
        actor = self.starting.pop(ref)
        try:
            info = self.ray.get(ref)
        except self.task_error as exc:
            _reraise(exc)
        except self.deaths_types as exc:
            logger.warning("stereo: a Ray worker died while starting (%s); starting another",
                           type(exc).__name__)
            self._lost(actor, "a worker starting", exc)
            return
        if info["version"] != __version__:
            raise DistributedError(
                f"Ray worker {info['pid']} on {info['host']} runs colmap-pvs {info['version']}, the driver "
                f"{__version__}: install the same version on every node"
            )
        self.info[id(actor)] = info
        logger.info("stereo: Ray worker pid %d on %s ready in %.1f s", info["pid"], info["host"],
                    info["seconds"])
        if self.plan is None:
            self.plan = info
        self.idle.append(actor)

    def wait_for_plan(self) -> dict:
        last_note = time.monotonic()
        while self.plan is None:
            if not self.starting:
                raise DistributedError("no Ray worker could start")
            done, _ = self.ray.wait(list(self.starting), num_returns=1, timeout=POLL_SECONDS)
            for ref in done:
                self.on_started(ref)
            if time.monotonic() - last_note > 60:
                last_note = time.monotonic()
                logger.warning("stereo: still waiting for Ray workers to start (%g CPUs free in the cluster)",
                               self.ray.available_resources().get("CPU", 0))
        return self.plan

    def run(self, graph: TaskGraph, bar, outcomes: dict) -> dict[Task, int]:
        """Hand out the tasks of ``graph`` until all finished, filling ``outcomes``; returns deaths per
        task. A later pass of a reference whose previous pass skipped it is not run (as locally)."""
        attempts: dict[Task, int] = {}
        while graph.remaining:
            while self.idle:
                task = graph.pop()
                if task is None:
                    break
                i = self.passes.index(task[1])
                prev = outcomes.get((task[0], self.passes[i - 1])) if i else None
                if prev is not None and prev.status == "skipped":  # recorded, so later passes skip too
                    if task[1] == "filled":  # never left for another reference's confirmation to read
                        remove_filled(Reference.of(Workspace(self.wcfg.workspace_path), task[0]))
                    outcomes[task] = RefOutcome(task[0], task[1], "skipped", prev.reason)
                    graph.finish(task)
                    bar.update(1)
                    continue
                actor = self.idle.popleft()
                self.running[actor.process.remote(*task)] = (actor, task, time.monotonic())
            if not self.running and not self.starting:
                why = "tasks wait for maps no task makes" if self.idle else "no Ray worker is alive"
                raise DistributedError(f"{graph.remaining} stereo task(s) left but {why}")
            done, _ = self.ray.wait([*self.running, *self.starting], num_returns=1, timeout=POLL_SECONDS)
            for ref in done:
                if ref in self.starting:
                    self.on_started(ref)
                    continue
                actor, task, _start = self.running.pop(ref)
                try:
                    outcome = self.ray.get(ref)
                except self.task_error as exc:
                    _reraise(exc)
                except self.deaths_types as exc:
                    why = "timed out" if ref in self.timed_out else type(exc).__name__
                    attempts[task] = attempts.get(task, 0) + 1
                    logger.warning("stereo: Ray worker %s died on %s/%s (%s); retry %d of %d elsewhere",
                                   self._worker_name(actor), *task, why, attempts[task],
                                   self.config.ray.max_retries)
                    if attempts[task] > self.config.ray.max_retries:
                        raise DistributedError(
                            f"reference {task[0]!r} ({task[1]} pass): its Ray worker died {attempts[task]} "
                            f"time(s) (last: {why}; ray_max_retries={self.config.ray.max_retries})"
                        ) from None
                    graph.requeue(task)
                    self._lost(actor, f"{task[0]}/{task[1]}", exc)
                    bar.set_postfix(retries=sum(attempts.values()))
                    continue
                outcomes[task] = outcome
                graph.finish(task)
                self.idle.append(actor)
                bar.update(1)
            if self.config.ray.task_timeout > 0:
                now = time.monotonic()
                for ref, (actor, task, start) in self.running.items():
                    if ref not in self.timed_out and now - start > self.config.ray.task_timeout:
                        logger.warning("stereo: %s/%s ran over ray_task_timeout=%g s; killing its worker",
                                       *task, self.config.ray.task_timeout)
                        self.timed_out.add(ref)
                        self.ray.kill(actor, no_restart=True)
        return attempts


def _result(ws: Workspace, plan: dict, passes: tuple[str, ...], outcomes: dict, wall: float):
    """The run's :class:`DistributedStereoResult` (fields as the local backend fills them) and
    ``fusion.cfg``: the references whose final maps exist."""
    result = DistributedStereoResult(workspace=ws, wall_seconds=wall)
    refs, aux = plan["references"], set(plan["auxiliary"])
    lists = {passes[0]: (result.processed, result.already_done, result.skipped)}
    if len(passes) > 1:
        lists[passes[1]] = (result.geometric_processed, result.geometric_done, result.geometric_skipped)
        result.auxiliary = list(plan["auxiliary"])
    if len(passes) > 2:
        lists[passes[2]] = (result.filled_processed, result.filled_done, result.filled_skipped)
        lists[passes[3]] = (result.confirm_processed, result.confirm_done, result.confirm_skipped)
    seconds = [out.seconds for out in outcomes.values() if out.status == "computed"]
    computed = {name for (name, _stage), out in outcomes.items()
                if out.status == "computed" and name not in aux}
    for stage, (processed, done, skipped) in lists.items():
        for name in refs:  # auxiliary images are reported in result.auxiliary only
            out = outcomes.get((name, stage))
            if out is None:
                continue  # skipped by an earlier pass
            if out.status == "computed":
                processed.append(name)
            elif out.status == "done":
                done.append(name)
            else:
                skipped[name] = out.reason
    result.sources = {n: s for n, s in plan["sources"].items() if s is not None and n not in result.skipped}
    kind = passes[min(1, len(passes) - 1)]  # the maps COLMAP fuses: the completion has no normals
    done = [n for n in refs if ws.depth_map_path(n, kind).is_file() and ws.normal_map_path(n, kind).is_file()]
    if not done:  # as the local backend: an error, and the previous fusion.cfg is kept
        reasons = "; ".join(f"{n}: {r}" for n, r in list(result.skipped.items())[:3])
        raise WorkspaceError(
            f"no depth map in {str(ws.stereo_dir)!r}: all {len(refs)} reference(s) were skipped ({reasons})"
        )
    write_fusion_cfg(ws.fusion_cfg, done)
    result.seconds_per_image = wall / len(computed) if computed else 0.0
    result.seconds_per_task = sum(seconds) / len(seconds) if seconds else 0.0
    sum_steps(outcomes.values(), into=result.timings)
    return result


def run_stereo_ray(config: StereoConfig, weights: Path | None = None) -> DistributedStereoResult:
    """:func:`colmap_pvs.stereo.run_stereo` on a Ray cluster (see the module docstring); every worker
    runs ``weights`` when given (they must be on the shared file system, as the workspace).

    Raises:
        DistributedError: Ray missing, no worker alive, or a reference whose workers died
            more than ``ray_max_retries`` times.
        WorkspaceError, CheckpointError: what a worker raised, e.g. when it cannot read the workspace.
    """
    ray = _import_ray()
    passes = stereo_passes(config)
    wall = Timer()
    handlers = _signal_handlers()
    started = _connect(ray, config)
    driver = None
    try:
        driver = _Driver(ray, config, passes, joined=bool(config.ray.address), weights=weights)
        for _ in range(driver.num_workers):
            driver.spawn()
        plan = driver.wait_for_plan()
        ws = Workspace(driver.wcfg.workspace_path)
        if not ws.stereo_dir.is_dir():
            raise WorkspaceError(f"the Ray driver cannot see {str(ws.stereo_dir)!r}; {SHARED_FS_HINT}")
        atomic_write_bytes(ws.stereo_dir / CONFIG_FILENAME, config_json_bytes(
            config, checkpoint_used=plan["checkpoint"], checkpoint_sha256=plan["checkpoint_sha256"],
            model_config=plan["model_config"]))
        remove_orphan_temps(ws.stereo_dir, recursive=True)  # e.g. from a run whose driver was killed
        refs: list[str] = plan["references"]
        if plan.get("patch_match_note"):
            logger.warning("stereo: %s", plan["patch_match_note"])
        graph = run_task_graph(config, passes, plan)
        outcomes: dict[Task, object] = {}
        bar = tqdm(total=len(graph.tasks), desc=f"stereo on Ray ({'+'.join(passes)})", unit="task")
        try:
            attempts = driver.run(graph, bar, outcomes)
        finally:
            bar.close()
            driver.kill_all()
        # Every worker is gone now: whatever temporary file is left (on any node) is an orphan.
        remove_orphan_temps(ws.stereo_dir, recursive=True, max_age_s=0.0)
        for name in refs:  # as locally: never keep a completion that no longer matches
            out = outcomes.get((name, "filled"))
            if "filled" not in passes or out is None or out.status == "skipped":
                remove_filled(Reference.of(ws, name))
        for stage in passes:
            logger.info("stereo %s", pass_summary(stage, outcomes.values()))
        result = _result(ws, plan, passes, outcomes, wall.elapsed())
        result.retried = {f"{n}/{s}": k for (n, s), k in attempts.items()}
        result.workers = len(driver.info)
        result.nodes = sorted({i["host"] for i in driver.info.values()})
        logger.info(
            "stereo (Ray, %d workers on %d node(s)): %d computed, %d already done, %d skipped, "
            "%d retried after a worker died, %.1f s", result.workers, len(result.nodes),
            len(result.processed), len(result.already_done), len(result.skipped), len(result.retried),
            result.wall_seconds,
        )
        return result
    finally:
        if driver is not None:
            driver.kill_all()
        if started:
            ray.shutdown()
            _restore_signal_handlers(handlers)

"""Transport batches (and phases) spread over a ``dask.distributed`` cluster (extra ``dask``).

The work unit is a group of batches of one geometry: the task calls
:func:`tetdose.transport.run.job.run_batches` on a worker and returns the batch rows. Every history
draws from its own counter-based stream ``seed_for(seed, stream, history)`` and every batch row
is summed in history order, so the rows — and the assembled :class:`DoseResult` — are bitwise
those of a local :func:`tetdose.transport.simulate` with the same settings, whatever the number
of workers, threads or tasks. Each geometry is scattered once (``broadcast=True``), each
distinct set of cross-section tables once per call, and all geometries' tasks are submitted at
once, so a cluster stays busy across breathing phases. Workers compile the kernels on first
use (numba's cache helps when ``NUMBA_CACHE_DIR`` is shared).

Example::

    with dask_client("local:2") as client:   # or dask_client("tcp://scheduler:8786")
        results = simulate_distributed(client, [phase0_mesh, phase1_mesh], plan,
                                       [settings, replace(settings, stream=1)])
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import Any

import numba
from tqdm.auto import tqdm

from tetdose._optional import import_optional
from tetdose._typing import FloatArray, IntArray
from tetdose.core.image import Image
from tetdose.core.mesh import TetMesh
from tetdose.errors import PlanError
from tetdose.plan.model import Plan
from tetdose.transport.geometry.world import World, as_world
from tetdose.transport.history.result import DoseResult
from tetdose.transport.run.job import (
    PROGRESS_DELAY_S,
    TransportJob,
    assemble,
    build_job,
    cross_sections,
    preflight,
    run_batches,
)
from tetdose.transport.run.settings import TransportSettings

_Rows = tuple[FloatArray, FloatArray, IntArray, FloatArray]


def _distributed() -> Any:  # noqa: ANN401 - module object
    return import_optional("distributed", "dask", "distributed transport")


@contextmanager
def dask_client(spec: str) -> Iterator[Any]:
    """A ``distributed.Client`` for ``spec``, closed on exit (with its cluster, if started).

    ``spec`` is a scheduler address (``tcp://host:8786``) or ``local:N``: a ``LocalCluster`` of
    N single-threaded worker processes on this machine (one numba thread each, no dashboard).
    Worker processes are spawned: a script that calls this must guard its entry point with
    ``if __name__ == "__main__":``.
    """
    distributed = _distributed()
    if spec.startswith("local"):
        n = spec.partition(":")[2] or "0"
        if not n.isdigit() or int(n) < 1:
            raise PlanError(f"--dask local:N needs a positive worker count N, got {spec!r}")
        # Single-threaded workers; each task limits numba to one thread itself (_timed_batches).
        # Not through the nanny's pre-spawn environment: that sets NUMBA_NUM_THREADS in this very
        # process while workers spawn, and numba then refuses to compile anything afterwards.
        with distributed.LocalCluster(n_workers=int(n), threads_per_worker=1, processes=True,
                                      dashboard_address=None) as cluster, \
                distributed.Client(cluster) as client:
            yield client
    else:
        try:
            client = distributed.Client(spec, timeout="20s")
        except OSError as exc:
            raise PlanError(f"cannot reach the dask scheduler at {spec!r} ({exc}); start one "
                            "(dask scheduler) or use --dask local:N") from exc
        with client:
            yield client


def _timed_batches(job: TransportJob, xs: Any, settings: TransportSettings, b_start: int,  # noqa: ANN401
                   b_stop: int) -> tuple[_Rows, float, float]:
    """:func:`run_batches` on a worker, with its wall and process CPU times [s].

    Numba uses one thread per task: dask runs as many tasks as the worker has threads.
    """
    numba.set_num_threads(1)
    t0, cpu0 = time.perf_counter(), time.process_time()
    rows = run_batches(job, xs, settings, b_start, b_stop)
    return rows, time.perf_counter() - t0, time.process_time() - cpu0


def simulate_distributed(client: Any,  # noqa: ANN401
                         geometries: World | TetMesh | Image | Sequence[World | TetMesh | Image],
                         plan: Plan, settings: TransportSettings | Sequence[TransportSettings],
                         *, labels: Image | None = None, batches_per_task: int = 1,
                         progress: bool | None = None) -> DoseResult | list[DoseResult]:
    """Run ``plan`` on one geometry or on each of a list (e.g. breathing phases) on ``client``.

    ``geometries``: a :class:`World` (mesh, density image or both), a :class:`TetMesh` with
    point_data ``density`` or a density :class:`Image` (with ``labels``), or a sequence of them.
    ``settings``: one for all, or one per geometry (a phase's random ``stream``). Returns one
    :class:`DoseResult`, or a list in the order of ``geometries``; each result's ``wall_s`` is
    the wall time of the whole call, ``extra["task_s"]`` the summed wall time of its own tasks on the
    workers and ``extra["task_cpu_s"]`` their workers' process CPU time (single-threaded workers: the tasks'
    own plus a little event-loop work; with several threads it includes concurrent tasks).
    """
    each = [settings] if isinstance(settings, TransportSettings) else list(settings)
    if any(st.target_uncertainty is not None for st in each):
        raise PlanError("a target uncertainty stops a run in this process; on dask give the "
                        "number of histories instead (target_uncertainty=None)")
    distributed = _distributed()
    if not isinstance(client, distributed.Client):
        raise PlanError(f"client must be a dask.distributed.Client, got {type(client).__name__}")
    if int(batches_per_task) < 1:
        raise PlanError(f"batches_per_task must be a positive integer, got {batches_per_task}")
    single = isinstance(geometries, World | TetMesh | Image)
    geoms = [geometries] if single else list(geometries)
    if not geoms:
        raise PlanError("give at least one geometry (mesh or density image)")
    each = [settings] * len(geoms) if isinstance(settings, TransportSettings) else list(settings)
    if len(each) != len(geoms):
        raise PlanError(f"{len(each)} settings for {len(geoms)} geometries; give one, or one "
                        "per geometry")
    t0 = time.perf_counter()
    jobs, tasks, scattered, xs_of = [], [], [], {}
    on_grids = []
    workers = sum(client.nthreads().values())
    for geom, st in zip(geoms, each, strict=True):
        job, on_grid = build_job(as_world(geom, labels), plan, st)
        preflight(job, cross_sections(job, st), st, workers)  # here, before any task is sent
        on_grids.append(on_grid)
        # Scatter lists (a bare NamedTuple goes element-wise) under fresh keys: with content keys
        # (hash=True) equal phases (10 % and 90 % of a symmetric cycle) share one key, and a task
        # was seen cancelled for "lost dependencies" (dask/distributed#4612; hash=False is the
        # workaround). The futures stay referenced in `scattered` until the rows are gathered.
        key = (tuple(job.names), st.energy_cutoff_mev)  # phases share their tables
        if key not in xs_of:
            xs_of[key] = client.scatter([cross_sections(job, st)], broadcast=True,
                                        hash=False)[0]
        job_f, xs_f = client.scatter([job], broadcast=True, hash=False)[0], xs_of[key]
        scattered.append(job_f)
        starts = range(0, st.n_batches, int(batches_per_task))
        tasks.append([client.submit(_timed_batches, job_f, xs_f, st, b0,
                                    min(st.n_batches, b0 + int(batches_per_task)), pure=False)
                      for b0 in starts])
        jobs.append(job)
    all_futures = [f for fs in tasks for f in fs]
    with tqdm(total=len(all_futures), unit="task", desc="transport (dask)", delay=PROGRESS_DELAY_S,
              disable=None if progress is None else not progress) as bar:
        for _ in distributed.as_completed(all_futures):
            bar.update(1)
    done = [client.gather(fs) for fs in tasks]
    wall = time.perf_counter() - t0
    results = []
    for job, on_grid, st, out in zip(jobs, on_grids, each, done, strict=True):
        results.append(assemble(job, on_grid, plan, st, [rows for rows, _, _ in out], wall,
                                {"task_s": sum(s for _, s, _ in out),
                                 "task_cpu_s": sum(c for _, _, c in out)}))
    return results[0] if single else results


def simulate_on(client: Any,  # noqa: ANN401
                geometries: World | TetMesh | Image | Sequence[World | TetMesh | Image],
                plan: Plan, settings: TransportSettings | Sequence[TransportSettings], *,
                labels: Image | None = None, batches_per_task: int = 1,
                progress: bool | None = None, desc: str = "dose per geometry"
                ) -> DoseResult | list[DoseResult]:
    """The one local-or-dask switch: :func:`simulate_distributed` on ``client``, or, with
    ``client=None``, :func:`tetdose.transport.simulate` on each geometry in turn here (a
    ``desc`` progress bar over a list). Arguments and return as :func:`simulate_distributed`;
    the doses are bitwise the same either way (module docstring)."""
    if client is not None:
        return simulate_distributed(client, geometries, plan, settings, labels=labels,
                                    batches_per_task=batches_per_task, progress=progress)
    from tetdose.transport import simulate

    if isinstance(geometries, World | TetMesh | Image):
        if not isinstance(settings, TransportSettings):
            raise PlanError("give one TransportSettings for one geometry")
        return simulate(geometries, plan, settings, labels=labels, progress=progress)
    geoms = list(geometries)
    each = [settings] * len(geoms) if isinstance(settings, TransportSettings) else list(settings)
    if len(each) != len(geoms):
        raise PlanError(f"{len(each)} settings for {len(geoms)} geometries; give one, or one "
                        "per geometry")
    return [simulate(g, plan, st, labels=labels, progress=False) for g, st in
            zip(tqdm(geoms, desc=desc, disable=not progress), each, strict=True)]

"""Transport batches (and phases) spread over a ``dask.distributed`` cluster (extra ``dask``).

The work unit is a group of batches of one geometry: the task calls
:func:`tetdose.transport.run_batches` on a worker and returns the batch rows. Every history
draws from its own counter-based stream ``seed_for(seed, stream, history)`` and every batch row
is summed in history order, so the rows — and the assembled :class:`DoseResult` — are bitwise
those of a local :func:`tetdose.transport.simulate` with the same settings, whatever the number
of workers, threads or tasks. Geometry and cross-section tables are scattered once per phase
(``broadcast=True``); workers compile the kernels on first use (numba's cache helps when
``NUMBA_CACHE_DIR`` is shared).

Example::

    from dask.distributed import Client
    client = Client("scheduler:8786")
    results = simulate_distributed(client, [phase0_mesh, phase1_mesh], plan, settings)
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

from tqdm.auto import tqdm

from tetdose.errors import PlanError, TetdoseError
from tetdose.image import Image
from tetdose.mesh import TetMesh
from tetdose.transport import (
    PROGRESS_DELAY_S,
    _assemble,
    _cross_sections,
    _mesh_job,
    _voxel_job,
    run_batches,
)
from tetdose.transport.model import Plan, TransportSettings
from tetdose.transport.result import DoseResult


def _distributed() -> Any:  # noqa: ANN401 - module object
    try:
        import distributed
    except ImportError as exc:
        raise TetdoseError(
            "distributed transport needs dask.distributed: install tetdose[dask] (pip install "
            "'tetdose[dask]' or pip install 'dask[distributed]')"
        ) from exc
    return distributed


def simulate_distributed(client: Any, geometries: TetMesh | Image | Sequence[TetMesh | Image],  # noqa: ANN401
                         plan: Plan, settings: TransportSettings, *,
                         labels: Image | None = None, batches_per_task: int = 1,
                         progress: bool | None = None) -> DoseResult | list[DoseResult]:
    """Run ``plan`` on one geometry or on each of a list (e.g. breathing phases) on ``client``.

    ``geometries``: a :class:`TetMesh` with point_data ``density`` or a density :class:`Image`
    (with ``labels``), or a sequence of them. Returns one :class:`DoseResult`, or a list in the
    order of ``geometries``; each result's ``wall_s`` is the wall time of the whole call.
    """
    distributed = _distributed()
    if not isinstance(client, distributed.Client):
        raise PlanError(f"client must be a dask.distributed.Client, got {type(client).__name__}")
    if int(batches_per_task) < 1:
        raise PlanError(f"batches_per_task must be a positive integer, got {batches_per_task}")
    single = isinstance(geometries, TetMesh | Image)
    geoms = [geometries] if single else list(geometries)
    if not geoms:
        raise PlanError("give at least one geometry (mesh or density image)")
    t0 = time.perf_counter()
    jobs, tasks = [], []
    for geom in geoms:
        if isinstance(geom, TetMesh):
            job = _mesh_job(geom, plan, settings, None)
        elif isinstance(geom, Image):
            job = _voxel_job(geom, plan, settings, labels)
        else:
            raise PlanError(f"geometries must be TetMesh or density Image, got {type(geom)}")
        job_f, xs_f = client.scatter([job, _cross_sections(job, settings)], broadcast=True)
        starts = range(0, settings.n_batches, int(batches_per_task))
        tasks.append([client.submit(run_batches, job_f, xs_f, settings, b0,
                                    min(settings.n_batches, b0 + int(batches_per_task)),
                                    pure=False) for b0 in starts])
        jobs.append(job)
    all_futures = [f for fs in tasks for f in fs]
    with tqdm(total=len(all_futures), unit="task", desc="transport (dask)", delay=PROGRESS_DELAY_S,
              disable=None if progress is None else not progress) as bar:
        for _ in distributed.as_completed(all_futures):
            bar.update(1)
    rows = [client.gather(fs) for fs in tasks]
    wall = time.perf_counter() - t0
    results = [_assemble(job, plan, settings, r, wall) for job, r in zip(jobs, rows, strict=True)]
    return results[0] if single else results

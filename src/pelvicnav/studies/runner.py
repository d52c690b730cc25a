"""One runner for every study: its cases on dask.distributed, each result stored as it finishes.

A :class:`Study` is its name, its settings (hashed into the store's key), its cases (seeded,
self-contained dicts with a ``case_id``: everything a worker needs travels with the case, so a
remote cluster needs no atlas) and a module-level function that runs one case and returns one row
or a list of rows. :func:`run_study`:

* opens the study's store (``OUT/store.sqlite``, :mod:`pelvicnav.studies.store`) and skips the
  cases it holds;
* runs the rest on a ``LocalCluster`` (one process per core, one thread each, BLAS, OpenMP and
  numba threads limited to one per worker), on an existing cluster (``scheduler``), or in this
  process (``workers=0``);
* stores each case the moment it finishes, and exports ``OUT/results.csv`` (one row per result
  row, a ``case_id`` column) at the end.

A case's result depends on the case alone, so a parallel run gives the same numbers as a serial
one with the same seed, and a killed run resumed gives the same numbers as one never killed.
"""

from __future__ import annotations

import csv
import io
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from pelvicnav.io.atomic import write_text
from pelvicnav.studies.store import ResultStore

__all__ = ["SCHEDULER_TIMEOUT_S", "WORKER_ENV", "Study", "flatten", "local_cluster", "run_study"]

SCHEDULER_TIMEOUT_S = 8
WORKER_ENV = {
    "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
    "NUMBA_NUM_THREADS": "1", "OMP_WAIT_POLICY": "passive",
}  # fmt: skip


@dataclass(frozen=True)
class Study:
    """A study: what the runner needs.

    Attributes
    ----------
    name : str
    settings : dict
        JSON-serialisable settings; a store made with other settings is refused.
    cases : tuple of dict
        Each with a unique ``case_id`` (str) and everything ``run_case`` needs.
    run_case : callable(dict) -> dict or list of dict
        A module-level function (workers import it).
    """

    name: str
    settings: dict
    cases: tuple[dict, ...]
    run_case: Callable[[dict], dict | list[dict]]

    def __post_init__(self) -> None:
        ids = [c.get("case_id") for c in self.cases]
        if any(not isinstance(i, str) for i in ids) or len(set(ids)) != len(ids):
            raise ValueError(f"study {self.name}: every case needs a unique string case_id")


def _run_one(run_case, case: dict):
    """Run one case with one thread for BLAS; returns (case_id, result, seconds)."""
    from threadpoolctl import threadpool_limits

    started = time.perf_counter()
    with threadpool_limits(1):
        result = run_case(case)
    return case["case_id"], result, time.perf_counter() - started


def _client(scheduler: str | None, workers: int | None):
    """A dask client: to ``scheduler``, or to a new LocalCluster of ``workers`` processes."""
    from distributed import Client

    if scheduler is not None:
        try:
            return Client(scheduler, timeout=f"{SCHEDULER_TIMEOUT_S}s")
        except (OSError, TimeoutError) as err:
            raise ValueError(
                f"cannot reach the dask scheduler at {scheduler} within {SCHEDULER_TIMEOUT_S} s "
                f"({type(err).__name__}); is it running, and is the address right?"
            ) from None
    return Client(local_cluster(workers))


def local_cluster(workers: int | None = None):
    """A ``LocalCluster`` as the studies use it: ``workers`` processes (default one per core),
    one thread each, BLAS, OpenMP and numba limited to one thread per worker."""
    import dask
    from distributed import LocalCluster

    n = workers or os.cpu_count() or 1
    # dask sets MALLOC_TRIM_THRESHOLD_=65536 in its workers (to give memory back to the OS);
    # that also fixes glibc's mmap threshold at 128 KiB, so every DRR batch and image buffer
    # is a fresh mmap with page faults: the quick registration study on one worker spent 6.3 s
    # in the kernel instead of 1.9 s (25 s against 23 s). The workers keep glibc's own tuning.
    with dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}):
        return LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                            dashboard_address=None, env=WORKER_ENV, silence_logs=40)  # fmt: skip


def run_study(
    study: Study,
    out: str | os.PathLike,
    *,
    scheduler: str | None = None,
    workers: int | None = None,
    force: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> list[tuple[str, object, float]]:
    """Run a study's missing cases and export ``results.csv``; returns every stored result.

    Parameters
    ----------
    scheduler : str, optional
        Address of an existing dask scheduler (``tcp://host:8786``).
    workers : int, optional
        LocalCluster processes (default: one per core); ``0`` runs in this process.
    force : bool
        Start afresh when the store holds the study with other settings.
    progress : callable(done, total), optional

    Raises
    ------
    ValueError
        An unreachable scheduler (within :data:`SCHEDULER_TIMEOUT_S`), a store made with other
        settings (:class:`~pelvicnav.studies.store.StoreMismatch`).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    order = [c["case_id"] for c in study.cases]
    with ResultStore(out / "store.sqlite", study.name, study.settings, force=force) as store:
        done = store.done()
        todo = [c for c in study.cases if c["case_id"] not in done]
        count = len(study.cases) - len(todo)
        if progress:
            progress(count, len(study.cases))
        for case_id, result, seconds in _execute(study.run_case, todo, scheduler, workers):
            store.put(case_id, result, seconds)
            count += 1
            if progress:
                progress(count, len(study.cases))
        results = store.results(order)
    write_text(out / "results.csv", _csv(flatten(results)))
    return results


def _execute(run_case, todo: list[dict], scheduler, workers):
    """Yield (case_id, result, seconds) as cases finish."""
    if not todo:
        return
    if workers == 0 and scheduler is None:
        for case in todo:
            yield _run_one(run_case, case)
        return
    import warnings

    from distributed import as_completed

    client = _client(scheduler, workers)
    try:
        with warnings.catch_warnings():
            # Cases carry their subject's meshes by design (workers need no atlas): tens of MB
            # for a study, which dask warns about. It is sent once, so the warning is noise.
            warnings.filterwarnings("ignore", message="Sending large graph")
            futures = client.map(_run_one, [run_case] * len(todo), todo, pure=False)
        for future in as_completed(futures):
            yield future.result()
    finally:
        cluster = client.cluster if scheduler is None else None
        client.close()
        if cluster is not None:
            cluster.close()


def flatten(results: Sequence[tuple[str, object, float]]) -> list[dict]:
    """One dict per result row, ``case_id`` first (a case may return several rows)."""
    rows = []
    for case_id, result, seconds in results:
        for row in result if isinstance(result, list) else [result]:
            rows.append({"case_id": case_id, **row, "case_seconds": seconds})
    return rows


def _csv(rows: list[dict]) -> str:
    fields = list(dict.fromkeys(k for r in rows for k in r)) or ["case_id"]
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=fields)
    writer.writeheader()
    writer.writerows(rows)
    return buf.getvalue()

"""Benchmark contract: warm up, repeat, report median and IQR (seconds), fixed seeds, JSON out."""

from __future__ import annotations

import os
import platform
import subprocess
import time
from collections.abc import Callable
from datetime import UTC, datetime

import numpy as np


def measure(fn: Callable[[], object], *, repeats: int = 7, warmup: int = 1) -> dict:
    """Time ``fn()``: median and interquartile range over ``repeats`` after ``warmup`` calls."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    q1, med, q3 = np.percentile(times, [25, 50, 75])
    return {
        "median_s": float(med),
        "iqr_s": float(q3 - q1),
        "min_s": float(min(times)),
        "repeats": repeats,
    }


def environment() -> dict:
    """What the numbers were measured on."""
    from threadpoolctl import threadpool_info

    try:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=False
        ).stdout.strip()
    except OSError:
        commit = ""
    return {
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "commit": commit,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "machine": platform.machine(),
        "cpu_count": os.cpu_count(),
        "affinity": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
        "numba_num_threads": os.environ.get("NUMBA_NUM_THREADS"),
        "blas": [
            {k: i.get(k) for k in ("internal_api", "num_threads", "version")}
            for i in threadpool_info()
        ],
    }

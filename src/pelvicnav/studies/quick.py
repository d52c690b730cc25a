"""Every study's ``--quick`` version, all at once, on one shared cluster.

``python -m pelvicnav.studies.quick OUT`` (``make studies-quick``, run by CI) starts one
``LocalCluster`` and launches every ``pelvicnav study NAME --out OUT/NAME --quick --scheduler
ADDRESS`` as its own command at the same time (the runtime study, which times steps in its own
process, without a scheduler and on one thread). The cluster's workers take the cases of every
study as they come, so neither core waits for a study's last case; the workers load the compiled
kernels once. Each command's output goes to ``OUT/NAME.log``; ``OUT/timings.md`` lists when each
command ended and the total (goal: two minutes on two cores, issue 16).
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

from pelvicnav.io.atomic import write_text
from pelvicnav.studies.runner import WORKER_ENV, local_cluster

__all__ = ["QUICK_STUDIES", "run_quick"]

# Longest first: the ones that run alone at the end bound the total.
QUICK_STUDIES = ("runtime", "segmentation", "capture-range", "registration", "dose", "fov",
                 "target-pose")  # fmt: skip
# No --scheduler option: it times each step where it runs, here with the workers' one-thread
# environment (beside them, more threads would only take turns).
_IN_PROCESS = ("runtime",)
GOAL_S = 120.0  # issue 16: every quick study together within two minutes on two cores


def _command(study: str, out: Path, address: str) -> list[str]:
    cmd = [sys.executable, "-c", "from pelvicnav.cli import main; main()", "study", study,
           "--out", str(out / study), "--quick"]  # fmt: skip
    return cmd if study in _IN_PROCESS else [*cmd, "--scheduler", address]


def run_quick(out: str | Path, *, workers: int | None = None,
              studies: tuple[str, ...] = QUICK_STUDIES) -> dict[str, float]:  # fmt: skip
    """Run every study's quick version concurrently; returns the seconds per study and in total.

    Raises
    ------
    RuntimeError
        A study's command failed (the message names each failed study and holds the end of its
        log); the others are waited for, and no ``timings.md`` is written.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    seconds: dict[str, float] = {}
    started = time.perf_counter()
    with local_cluster(workers) as cluster:
        seconds["cluster start"] = time.perf_counter() - started
        running = {}
        for study in studies:
            fh = open(out / f"{study}.log", "w")  # noqa: SIM115 (closed when it ends)
            cmd = _command(study, out, cluster.scheduler_address)
            env = {**os.environ, **WORKER_ENV} if study in _IN_PROCESS else None
            running[study] = (subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT, env=env),
                              fh)  # fmt: skip
        failed = _wait(running, seconds, started)
    if failed:
        tails = [
            f"pelvicnav study {s} --quick failed ({out / f'{s}.log'}):\n"
            + (out / f"{s}.log").read_text(errors="replace")[-3000:]
            for s in failed
        ]
        raise RuntimeError("\n\n".join(tails))
    seconds["total"] = time.perf_counter() - started
    lines = ["# Quick studies", "", f"Run concurrently on one cluster; goal {GOAL_S:g} s in total.",
             "", "| step | ended after, s |", "|---|---|"]  # fmt: skip
    lines += [f"| {k} | {v:.1f} |" for k, v in seconds.items()]
    write_text(out / "timings.md", "\n".join(lines) + "\n")
    return seconds


def _wait(running: dict, seconds: dict[str, float], started: float) -> list[str]:
    """Wait for every command, noting when each ended; returns the failed studies."""
    failed = []
    while running:
        for study, (proc, fh) in list(running.items()):
            if proc.poll() is None:
                continue
            fh.close()
            del running[study]
            seconds[study] = time.perf_counter() - started
            status = "done" if proc.returncode == 0 else f"FAILED (exit {proc.returncode})"
            print(f"study {study} --quick: {status} at {seconds[study]:.0f} s", flush=True)
            if proc.returncode != 0:
                failed.append(study)
        time.sleep(0.2)
    return failed


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit("usage: python -m pelvicnav.studies.quick OUT")
    try:
        total = run_quick(sys.argv[1])["total"]
    except RuntimeError as err:
        sys.exit(str(err))
    print(f"all quick studies: {total:.0f} s (goal {GOAL_S:g} s)")

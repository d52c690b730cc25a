"""Every study's ``--quick`` version, one after the other, on one shared cluster.

``python -m pelvicnav.studies.quick OUT`` (``make studies-quick``) starts one ``LocalCluster``
and runs each ``pelvicnav study NAME --out OUT/NAME --quick --scheduler ADDRESS`` as its own
command (the runtime study, which times steps in its own process, without a scheduler). The
workers stay up between studies, so each study pays for its command's imports but not for
starting a cluster and loading the compiled kernels again. Each command's output goes to
``OUT/NAME.log``; ``OUT/timings.md`` lists the seconds per study.
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

from pelvicnav.io.atomic import write_text
from pelvicnav.studies.runner import local_cluster

__all__ = ["QUICK_STUDIES", "run_quick"]

QUICK_STUDIES = ("target-pose", "registration", "capture-range", "dose", "fov", "runtime",
                 "segmentation")  # fmt: skip
_IN_PROCESS = ("runtime",)  # no --scheduler option: it times each step where it runs


def _command(study: str, out: Path, address: str) -> list[str]:
    cmd = [sys.executable, "-c", "from pelvicnav.cli import main; main()", "study", study,
           "--out", str(out / study), "--quick"]  # fmt: skip
    return cmd if study in _IN_PROCESS else [*cmd, "--scheduler", address]


def run_quick(out: str | Path, *, workers: int | None = None,
              studies: tuple[str, ...] = QUICK_STUDIES) -> dict[str, float]:  # fmt: skip
    """Run each study's quick version; returns the seconds per study.

    Raises
    ------
    RuntimeError
        A study's command failed (the message holds the end of its log).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    seconds: dict[str, float] = {}
    started = time.perf_counter()
    with local_cluster(workers) as cluster:
        seconds["cluster start"] = time.perf_counter() - started
        for study in studies:
            t0 = time.perf_counter()
            log = out / f"{study}.log"
            with open(log, "w") as fh:
                rc = subprocess.run(_command(study, out, cluster.scheduler_address),
                                    stdout=fh, stderr=subprocess.STDOUT).returncode  # fmt: skip
            seconds[study] = time.perf_counter() - t0
            print(f"study {study} --quick: {seconds[study]:.0f} s "
                  f"({time.perf_counter() - started:.0f} s so far)", flush=True)  # fmt: skip
            if rc != 0:
                tail = log.read_text(errors="replace")[-3000:]
                raise RuntimeError(f"pelvicnav study {study} --quick failed ({log}):\n{tail}")
    seconds["total"] = time.perf_counter() - started
    lines = ["# Quick studies", "", "| step | seconds |", "|---|---|"]
    lines += [f"| {k} | {v:.1f} |" for k, v in seconds.items()]
    write_text(out / "timings.md", "\n".join(lines) + "\n")
    return seconds


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit("usage: python -m pelvicnav.studies.quick OUT")
    try:
        run_quick(sys.argv[1])
    except RuntimeError as err:
        sys.exit(str(err))

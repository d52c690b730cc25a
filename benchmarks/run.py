"""Run every ``benchmarks/bench_*.py`` and write one JSON file each under ``--out``.

Usage: ``python -m benchmarks.run --out benchmarks/results [--only atlas]``
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "passive")

from benchmarks.harness import environment


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results"))
    parser.add_argument("--only", default=None, help="run only bench_<name>.py")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    names = sorted(p.stem for p in Path(__file__).parent.glob("bench_*.py"))
    if args.only:
        names = [n for n in names if n == f"bench_{args.only}"]
    env = environment()
    for name in names:
        module = importlib.import_module(f"benchmarks.{name}")
        result = {"benchmark": name, "environment": env, "results": module.run()}
        path = args.out / f"{name.removeprefix('bench_')}.json"
        tmp = path.with_suffix(".json.part")
        tmp.write_text(json.dumps(result, indent=2) + "\n")
        tmp.replace(path)
        print(f"{path}:")
        for key, value in result["results"].items():
            summary = (
                value
                if not isinstance(value, dict)
                else {k: v for k, v in value.items() if k in ("median_s", "iqr_s", "meets_target")}
            )
            print(f"  {key}: {summary}")


if __name__ == "__main__":
    main()

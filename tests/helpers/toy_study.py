"""A study cheap enough to test the runner with: each case draws a number from its seed."""

from __future__ import annotations

import time

import numpy as np

from pelvicnav.studies.runner import Study


def run_toy(case: dict) -> dict:
    time.sleep(case["sleep"])
    rng = np.random.default_rng(case["seed"])
    return {"seed": case["seed"], "value": float(rng.normal()), "rows": int(rng.integers(9))}


def toy_study(n: int = 8, sleep: float = 0.0, scale: float = 1.0) -> Study:
    cases = tuple({"case_id": f"{i:03d}", "seed": i, "sleep": sleep} for i in range(n))
    return Study("toy", {"n": n, "scale": scale}, cases, run_toy)

"""`python -m app.warmup`: compile the numba kernels once, ahead of the first request.

Fusion and planning kernels are compiled at their first call and cached in
``NUMBA_CACHE_DIR``; the Docker build runs this so that a new container's first
scan and first plan do not wait seconds for the compiler.
"""

from __future__ import annotations

import time

import numpy as np

import planning
from fuzzyocc import BayesMap, FuzzyMap, GridSpec, LaserScan, PointCloud, SensorModel


def warm_up() -> float:
    """Fuse a scan into small 2-D and 3-D maps of both models and plan in every state space; the seconds taken."""
    started = time.perf_counter()
    scan = LaserScan(pose=(1.0, 1.0, 0.0), angle_min=-1.0, angle_increment=0.1, ranges=np.full(21, 0.7),
                     range_min=0.05, range_max=5.0)
    cloud = PointCloud(points=np.array([[1.7, 1.0, 1.0], [1.7, 1.2, 1.1]]), origin=(1.0, 1.0, 1.0), range_max=5.0)
    for model in (FuzzyMap, BayesMap):
        flat = model(GridSpec(origin=(0.0, 0.0), size=(2.0, 2.0), resolution=0.1), SensorModel())
        flat.integrate_batch([scan])
        flat.risk_at(np.array([[1.5, 1.0]]))
        solid = model(GridSpec(origin=(0.0, 0.0, 0.0), size=(2.0, 2.0, 2.0), resolution=0.1), SensorModel())
        solid.integrate_batch([cloud])
        solid.risk()
    planning.warm_up()
    return time.perf_counter() - started


if __name__ == "__main__":
    print(f"numba kernels compiled and cached in {warm_up():.1f} s")

"""The fusion kernels, compiled (or loaded from numba's cache) before the first scan needs them.

numba compiles a kernel at its first call, for the types of that call, and caches the machine
code in ``NUMBA_CACHE_DIR`` (the service points it into its data directory). A cold cache costs
tens of seconds of compilation, a warm one a fraction of a second. The service runs
``warm_fusion`` in a fusion thread as it starts (its readiness, ``GET /ready``, waits for it). The planner
kernels are warmed in the planner workers (``app.plans.pool``), and here those of a path check, which runs
in the server's read threads (``app.plans.path_check``).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from app.formats import exports
from fuzzyocc import BayesMap, FuzzyMap, GridSpec, LaserScan, PointCloud, SensorModel, cast_work


def _fuse_2d(model: type[FuzzyMap] | type[BayesMap]) -> None:
    scan = LaserScan(pose=(1.0, 1.0, 0.0), angle_min=-1.0, angle_increment=0.1, ranges=np.full(21, 0.7),
                     range_min=0.05, range_max=5.0)
    spec = GridSpec(origin=(0.0, 0.0), size=(2.0, 2.0), resolution=0.1)
    cast_work(spec, [scan])  # the service estimates every batch before it is stored
    flat = model(spec, SensorModel())
    flat.integrate_batch([scan])
    flat.risk_at(np.array([[1.5, 1.0]]))
    flat.risk()
    flat.observed()  # every grid read asks for it: loaded from the cache at the first, 0.2 s of the GIL
    flat.plane_lookup(exports.occupancy_lut(), -1)  # a 2-D map's OccupancyGrid (a read-only table, as served)
    # a map's first snapshot copies it: compiled there, 0.3-0.7 s of the GIL that every request waited for
    model.from_arrays(spec, SensorModel(), flat.to_arrays())
    model.from_arrays(spec, SensorModel(), flat.snapshot_arrays())


def _fuse_3d(model: type[FuzzyMap] | type[BayesMap]) -> None:
    cloud = PointCloud(points=np.array([[1.7, 1.0, 1.0], [1.7, 1.2, 1.1]]), origin=(1.0, 1.0, 1.0), range_max=5.0)
    spec = GridSpec(origin=(0.0, 0.0, 0.0), size=(2.0, 2.0, 2.0), resolution=0.1)
    cast_work(spec, [cloud])
    solid = model(spec, SensorModel())
    solid.integrate_batch([cloud])
    solid.risk_at(np.array([[1.5, 1.0, 1.0]]))
    solid.risk()
    solid.observed()
    model.from_arrays(spec, SensorModel(), solid.to_arrays())
    model.from_arrays(spec, SensorModel(), solid.snapshot_arrays())


def _check_paths() -> None:
    """Paths checked on small 2-D and 3-D fields, with unknown space allowed and not: the walk and the dilations."""
    from planning import RiskField
    from planning.path_check import check_path

    for shape in ((6, 6), (6, 6, 3)):
        observed = np.ones(shape, bool)
        observed[-1] = False
        field = RiskField(np.full(shape, 0.2, np.float32), 0.1, (0.0,) * len(shape), observed=observed)
        for allow_unknown in (True, False):
            check_path(field, [[0.15] * len(shape), [0.45] * len(shape)], robot_radius=0.1,
                       allow_unknown=allow_unknown)


#: In the order a robot's first requests need them: a LaserScan on a 2-D fuzzy map first.
STEPS: tuple[tuple[str, Callable[[], None]], ...] = (
    ("2-D fuzzy fusion", lambda: _fuse_2d(FuzzyMap)),
    ("3-D fuzzy fusion", lambda: _fuse_3d(FuzzyMap)),
    ("2-D Bayes fusion", lambda: _fuse_2d(BayesMap)),
    ("3-D Bayes fusion", lambda: _fuse_3d(BayesMap)),
    ("path checks", _check_paths),
)


def warm_fusion(progress: Callable[[str, float], None] | None = None) -> float:
    """Fuse a scan into small maps of every kind; ``progress(step, seconds)`` after each step; the seconds taken."""
    started = time.perf_counter()
    for name, step in STEPS:
        step_started = time.perf_counter()
        step()
        if progress is not None:
            progress(name, time.perf_counter() - step_started)
    return time.perf_counter() - started

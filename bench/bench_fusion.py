"""Fusion throughput and memory of FuzzyMap and BayesMap against OctoMap, measured in the same run.

    python -m bench.bench_fusion [--quick] [--seed N] [--repeat N]      (from the repository root)

Two synthetic scenes, generated from a fixed seed with exact ray-box intersection and 3 cm
Gaussian range noise (the maps' ``range_sigma``):

(a) a 20 m x 20 m room with walls and boxes, 30 planar scans of 1080 beams over 270 deg
    (max range 30 m), fused at 0.05 m into 2-D maps; OctoMap gets the same beams as points
    at z = 0 in a 3-D OcTree at 0.05 m (it has no 2-D mode);
(b) a 20 x 20 x 4 m room with walls, floor, ceiling and boxes, 10 sweeps of 64 x 1024 rays
    (an Ouster OS1-64 pattern), fused at 0.1 m into 3-D maps and into an OcTree at 0.1 m.

Each scan is one integrate call (``integrate_scan`` / ``integrate_points`` /
``OcTree.insertPointCloud``), as a robot streams them. ``Fuzzy/growing`` is the default engine's
``FuzzyMap`` on a growing map (``LatticeSpec``: no box, cells on the lattice of the frame's origin,
blocks allocated as rays reach them) fed the same scans; its cells are those of the fixed box,
checked by comparing the two maps' risk over the growing map's bounds. Numba compile time is excluded: every
model is warmed up on a tiny map first. OctoMap's "cells traversed" are counted with our
exact traversal over the same segments (sensor to end point) since it does not report them.
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import cast

import numpy as np

from fuzzyocc import BayesMap, FuzzyEngine, FuzzyMap, GridSpec, LatticeSpec, SensorModel, presets
from fuzzyocc.engine import _defuzzify_tables
from fuzzyocc.raycast import cast_rays

RANGE_MAX_M = 30.0
RANGE_NOISE_M = 0.03  # the range_sigma the maps are given
# Scene (a) takes a tenth of a second a run: a burst of other work on a shared machine decided its
# figure with 3 runs (the same code read 4.9x to 6.7x OctoMap's rays/s), so it gets three times as many.
PLANAR_RUNS_PER_REPEAT = 3


@dataclass
class Scene:
    name: str
    spec: GridSpec
    origins: list[np.ndarray]  # per scan, (D,)
    points: list[np.ndarray]  # per scan, (N, D) beam end points (map frame)
    ranges: list[np.ndarray]  # per scan, (N,) for the planar scans
    angles: tuple[float, float] | None  # (angle_min, angle_increment) of planar scans


def _ray_boxes(origin: np.ndarray, dirs: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Range to the first box face along each ray (slab method), inf where none is hit."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / dirs[:, None, :]
        ta = (lo[None] - origin) * inv
        tb = (hi[None] - origin) * inv
    t_near = np.nanmax(np.minimum(ta, tb), axis=2)
    t_far = np.nanmin(np.maximum(ta, tb), axis=2)
    hit = (t_near <= t_far) & (t_near > 0.0)
    return np.where(hit, t_near, np.inf).min(axis=1)


def _room_boxes(rng: np.random.Generator, ndim: int) -> tuple[np.ndarray, np.ndarray]:
    size = np.array([20.0, 20.0, 4.0][:ndim])
    wall = 0.2
    lo, hi = [], []
    for axis in range(ndim):  # two walls (or floor and ceiling) per axis
        for side in (0.0, 1.0):
            a = np.full(ndim, -wall)
            b = size + wall
            a[axis] = -wall if side == 0.0 else size[axis]
            b[axis] = 0.0 if side == 0.0 else size[axis] + wall
            lo.append(a)
            hi.append(b)
    for _ in range(12):  # boxes standing on the floor
        c = rng.uniform(2.0, 18.0, 2)
        half = rng.uniform(0.2, 0.8, 2)
        a, b = np.zeros(ndim), np.zeros(ndim)
        a[:2], b[:2] = c - half, c + half
        if ndim == 3:
            a[2], b[2] = 0.0, rng.uniform(0.5, 2.0)
        lo.append(a)
        hi.append(b)
    return np.array(lo), np.array(hi)


def _free_position(rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray, ndim: int) -> np.ndarray:
    while True:
        p = rng.uniform(1.0, 19.0, ndim)
        if ndim == 3:
            p[2] = rng.uniform(1.0, 2.0)
        if not np.any(np.all((p > lo - 0.3) & (p < hi + 0.3), axis=1)):
            return p


def planar_scene(rng: np.random.Generator, n_scans: int, beams: int = 1080, fov_deg: float = 270.0) -> Scene:
    lo, hi = _room_boxes(rng, 2)
    inc = np.radians(fov_deg) / beams
    angle_min = -np.radians(fov_deg) / 2
    origins, points, ranges = [], [], []
    for _ in range(n_scans):
        p = _free_position(rng, lo, hi, 2)
        theta = rng.uniform(-np.pi, np.pi)
        a = theta + angle_min + inc * np.arange(beams)
        dirs = np.stack([np.cos(a), np.sin(a)], axis=1)
        r = _ray_boxes(p, dirs, lo, hi) + rng.normal(0.0, RANGE_NOISE_M, beams)
        r = np.where(r < RANGE_MAX_M, r, np.inf)
        origins.append(np.array([p[0], p[1], theta]))
        ranges.append(r)
        points.append(p + dirs * np.minimum(r, RANGE_MAX_M)[:, None])
    spec = GridSpec(origin=(-0.5, -0.5), size=(21.0, 21.0), resolution=0.05)
    return Scene("(a) 2-D room, 1080-beam planar scans", spec, origins, points, ranges, (angle_min, inc))


def lidar_scene(rng: np.random.Generator, n_scans: int, rings: int = 64, columns: int = 1024) -> Scene:
    lo, hi = _room_boxes(rng, 3)
    elev = np.radians(np.linspace(-16.6, 16.6, rings))
    azim = np.linspace(0.0, 2 * np.pi, columns, endpoint=False)
    el, az = np.meshgrid(elev, azim, indexing="ij")
    dirs_sensor = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1).reshape(-1, 3)
    origins, points = [], []
    for _ in range(n_scans):
        p = _free_position(rng, lo, hi, 3)
        yaw = rng.uniform(-np.pi, np.pi)
        rot = np.array([[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0], [0.0, 0.0, 1.0]])
        dirs = dirs_sensor @ rot.T
        r = np.concatenate([_ray_boxes(p, d, lo, hi) for d in np.array_split(dirs, 16)])
        r = r + rng.normal(0.0, RANGE_NOISE_M, r.size)
        origins.append(p)
        points.append(p + dirs * r[:, None])
    spec = GridSpec(origin=(-0.5, -0.5, -0.5), size=(21.0, 21.0, 5.0), resolution=0.1)
    return Scene("(b) 3-D room, 64 x 1024 lidar sweeps", spec, origins, points, [], None)


@dataclass
class Run:
    wall_s: float
    cpu_s: float  # this process, all threads (OctoMap's OpenMP workers too)
    rays: int
    nbytes: int  # persistent state (OctoMap: the tree)
    resident: int  # everything held between calls (OctoMap: the tree)
    traversed: int = 0
    held_cells: int = 0  # cells held in memory (OctoMap: none counted)


class Clock:
    """Wall and process CPU seconds of a ``with`` block (``wall``, ``cpu`` once it ends)."""

    def __enter__(self) -> Clock:
        self.wall, self.cpu = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc: object) -> None:
        self.wall, self.cpu = time.perf_counter() - self.wall, time.process_time() - self.cpu


def _integrate(factory: Callable[[GridSpec, SensorModel], FuzzyMap | BayesMap], scene: Scene,
               kept: dict[str, FuzzyMap | BayesMap] | None = None, label: str = "") -> Run:
    m = factory(scene.spec, SensorModel(range_sigma=RANGE_NOISE_M))
    rays = traversed = 0
    with Clock() as clock:
        for s in range(len(scene.origins)):
            if scene.angles is not None:
                x, y, theta = scene.origins[s]
                st = m.integrate_scan(pose=(x, y, theta), angle_min=scene.angles[0],
                                      angle_increment=scene.angles[1], ranges=scene.ranges[s],
                                      range_min=0.05, range_max=RANGE_MAX_M)
            else:
                st = m.integrate_points(scene.points[s], origin=scene.origins[s], range_max=RANGE_MAX_M)
            rays += st.rays
            traversed += st.cells_traversed
        m.risk()  # a reader pays for the defuzzification of what changed: count it
    if kept is not None:
        kept[label] = m
    return Run(clock.wall, clock.cpu, rays, m.state_nbytes(), m.resident_nbytes(), traversed,
               m.held_cells() if isinstance(m, FuzzyMap) else m.spec.num_cells)


def _octomap(scene: Scene) -> Run:
    import octomap  # the bench extra: octomap-python

    tree = octomap.OcTree(scene.spec.resolution)
    pts3, org3 = [], []
    for s in range(len(scene.origins)):
        pts = scene.points[s]
        org = scene.origins[s][:2] if scene.angles is not None else scene.origins[s]
        if pts.shape[1] == 2:
            pts = np.concatenate([pts, np.zeros((len(pts), 1))], axis=1)
            org = np.append(org, 0.0)
        pts3.append(np.ascontiguousarray(pts, dtype=np.float64))
        org3.append(np.asarray(org, dtype=np.float64))
    with Clock() as clock:
        for pts, org in zip(pts3, org3):
            tree.insertPointCloud(pts, org, maxrange=RANGE_MAX_M)
    usage = int(tree.memoryUsage())
    return Run(clock.wall, clock.cpu, sum(len(p) for p in pts3), usage, usage)


def _segment_cells(scene: Scene) -> int:
    """Cells on the segments sensor -> end point, by our exact traversal (what OctoMap walks)."""
    total = 0
    for s in range(len(scene.origins)):
        org = scene.origins[s][: scene.spec.ndim]
        off = scene.points[s] - org
        dist = np.linalg.norm(off, axis=1)
        n = len(dist)
        res = cast_rays(scene.spec, np.repeat(org[None], n, axis=0), off / dist[:, None], dist,
                        measured=np.full(n, np.nan), sigma=np.ones(n), ray_offsets=np.array([0, n]),
                        unknown_from=np.inf)
        total += int(res.cells_traversed.sum())
    return total


def _lut_nbytes(engine: FuzzyEngine) -> int:
    tables = _defuzzify_tables(engine)
    return 0 if tables is None else sum(a.nbytes for a in tables)


def _paper_map(spec: GridSpec, sensor: SensorModel) -> FuzzyMap:
    return FuzzyMap(spec, sensor, FuzzyEngine.paper())


def _growing_map(spec: GridSpec, sensor: SensorModel) -> FuzzyMap:
    """The default engine's map with no box, at ``spec``'s resolution (its cells are ``spec``'s: the box's origin
    lies on the lattice)."""
    return FuzzyMap(LatticeSpec(spec.ndim, spec.resolution), sensor)


def _same_cells(fixed: FuzzyMap, growing: FuzzyMap) -> bool:
    """Whether the fixed map's risk and observed cells over the growing map's bounds are the growing map's."""
    bounds = growing.bounds()
    if bounds is None:
        return False
    half = 0.5 * bounds.resolution
    window = fixed.window([o + half for o in bounds.origin], [u - half for u in bounds.upper])
    return (window is not None and window.shape == bounds.shape
            and np.array_equal(fixed.risk(window), growing.risk())
            and np.array_equal(fixed.observed(window), growing.observed()))


def _warm_up() -> None:
    for spec in (GridSpec(origin=(0.0, 0.0), size=(1.0, 1.0), resolution=0.1),
                 GridSpec(origin=(0.0, 0.0, 0.0), size=(1.0, 1.0, 1.0), resolution=0.1)):
        for m in (FuzzyMap(spec, SensorModel()), BayesMap(spec, SensorModel()), _growing_map(spec, SensorModel())):
            pts = np.full((4, spec.ndim), 0.8)
            m.integrate_points(pts, origin=np.full(spec.ndim, 0.15), range_max=0.5)
            m.integrate_points(pts, origin=np.full(spec.ndim, 0.15), range_max=5.0)
            if spec.ndim == 2:
                m.integrate_scan(pose=(0.5, 0.5, 0.0), angle_min=0.0, angle_increment=0.1, ranges=[0.3, np.inf],
                                 range_min=0.0, range_max=1.0)
            m.risk()


def run(scene: Scene, repeat: int) -> None:
    print(f"\n{scene.name}: {len(scene.origins)} scans, {sum(len(p) for p in scene.points)} rays, "
          f"grid {scene.spec.shape} at {scene.spec.resolution} m")
    kept: dict[str, FuzzyMap | BayesMap] = {}  # the last map of each model, to compare their cells
    models = {
        "FuzzyMap": lambda: _integrate(FuzzyMap, scene, kept, "FuzzyMap"),
        "Fuzzy/growing": lambda: _integrate(_growing_map, scene, kept, "Fuzzy/growing"),
        "Fuzzy/paper": lambda: _integrate(_paper_map, scene),
        "BayesMap": lambda: _integrate(BayesMap, scene),
        "OctoMap": lambda: _octomap(scene),
    }
    # Rounds interleave the models, each round starting one model later, so that a burst of other work on the
    # machine, or what one model leaves behind for the next (freed memory, a cold cache), hits them alike.
    runs: dict[str, list[Run]] = {label: [] for label in models}
    labels = list(models)
    for r in range(repeat):
        for label in labels[r % len(labels):] + labels[: r % len(labels)]:
            runs[label].append(models[label]())
    best = {label: min(r, key=lambda x: x.wall_s) for label, r in runs.items()}
    cpu = {label: min(x.cpu_s for x in r) for label, r in runs.items()}
    best["OctoMap"].traversed = _segment_cells(scene)
    octo = best["OctoMap"]
    cells = scene.spec.num_cells
    print(f"  {'model':13s} {'wall s':>7s} {'cpu s':>7s} {'rays/s':>10s} {'cells/s':>12s} "
          f"{'rays/s vs OctoMap':>18s} {'(by cpu s)':>11s} {'state MB':>9s} {'B/cell':>6s} {'vs OctoMap':>10s} "
          f"{'resident MB':>11s} {'B/cell':>6s} {'vs OctoMap':>10s}")
    for label, r in best.items():
        print(f"  {label:13s} {r.wall_s:7.3f} {cpu[label]:7.3f} {r.rays / r.wall_s:10,.0f} "
              f"{r.traversed / r.wall_s:12,.0f} {octo.wall_s / r.wall_s:17.2f}x {cpu['OctoMap'] / cpu[label]:10.2f}x "
              f"{r.nbytes / 1e6:9.2f} {r.nbytes / cells:6.2f} {r.nbytes / octo.nbytes:9.2f}x "
              f"{r.resident / 1e6:11.2f} {r.resident / cells:6.2f} {r.resident / octo.resident:9.2f}x")
    fixed, growing = best["FuzzyMap"], best["Fuzzy/growing"]
    same = _same_cells(cast(FuzzyMap, kept["FuzzyMap"]), cast(FuzzyMap, kept["Fuzzy/growing"]))
    print(f"  growing map: rays/s {fixed.wall_s / growing.wall_s:.2f}x the fixed FuzzyMap's (target >= 0.9x; by cpu "
          f"s {cpu['FuzzyMap'] / cpu['Fuzzy/growing']:.2f}x), {octo.wall_s / growing.wall_s:.2f}x OctoMap's (target >= "
          f"5x); held cells {growing.held_cells:,} (fixed: {fixed.held_cells:,} of the box's {cells:,}), state "
          f"{growing.nbytes:,} B = {growing.nbytes / octo.nbytes:.2f}x OctoMap's tree (target <= 1x); "
          f"cells equal to the fixed map's over its bounds: {'yes' if same else 'NO'}")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a smaller run: 6 planar scans, 2 lidar sweeps")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--repeat", type=int, default=3,
                        help=f"runs per model of scene (b), {PLANAR_RUNS_PER_REPEAT}x as many of (a); the fastest is reported")
    args = parser.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    planar = planar_scene(rng, 6 if args.quick else 30)
    lidar = lidar_scene(rng, 2 if args.quick else 10)
    t0 = time.perf_counter()
    _warm_up()
    print(f"numba warm-up on tiny maps: {time.perf_counter() - t0:.1f} s (excluded from the timings below)")
    print("state MB: FuzzyMap/BayesMap state_nbytes(), the persistent state (cell states, observed bits); "
          "resident MB: resident_nbytes(), all a map holds between calls (plus the 16-bit risk cache); "
          "OctoMap: tree.memoryUsage() for both; B/cell: per cell of our dense grid; FuzzyMap keeps a block of "
          "cells in one state (4x4x4 in 3-D, 4x4 in 2-D) once, so its B/cell is below its L bytes of state")
    default = presets.preset(presets.DEFAULT_PRESET)
    print(f"FuzzyMap: the default engine ({presets.DEFAULT_PRESET!r}, {default.num_labels} labels) in the scene's box; "
          "Fuzzy/growing: the same on a growing map (LatticeSpec, no box); Fuzzy/paper: the paper's engine "
          "(FuzzyEngine.paper(), 7 labels)")
    print(f"not in any row: the engines' defuzzification tables, {_lut_nbytes(default) / 1e6:.1f} MB "
          f"({presets.DEFAULT_PRESET}) and {_lut_nbytes(FuzzyEngine.paper()) / 1e6:.1f} MB (paper) once per process "
          "(shared by every FuzzyMap of that engine); arrays an integrate call allocates and frees")
    print(f"wall s: the fastest of {PLANAR_RUNS_PER_REPEAT * args.repeat} (scene a) or {args.repeat} (scene b) "
          "interleaved runs (a fresh map each), one integrate call per "
          "scan, plus one risk() read at the end (defuzzification of the changed cells); cpu s: the least "
          "process CPU time of those runs (all threads); rays/s and cells/s are by wall time")
    print("OctoMap cells/s: cells on the same segments counted by our traversal (OctoMap does not report them)")
    print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f} (other work skews all rows alike)")
    run(planar, PLANAR_RUNS_PER_REPEAT * args.repeat)
    run(lidar, args.repeat)
    print(f"\nload average at the end: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()

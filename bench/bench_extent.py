"""Fusion costs what the rays cost, not what the extent costs; a growing map's memory against OctoMap's.

    python -m bench.bench_extent [--logs acapulco,seattle | all] [--rounds N] [--only speed,memory,ouster]
                                 [--data DIR]                                     (from the repository root)

Three parts, each printed beside its peer measured in the same run:

speed   The same scans of recorded CARMEN logs (``--logs``) fused with the default engine at 0.05 m, in
        batches of 16 as a robot streams them, into (a) the log's own box: the bounds of the growing map of
        the same scans, so that the rays walk the same cells; (b) a 400 x 400 m box around it, its corner on
        the same lattice; (c) a growing map (``LatticeSpec``). Rounds interleave the three, each round
        starting with the next, and the fastest of ``--rounds`` (more for a short log) is kept, wall and CPU
        time apart. Prints scans/s, the ratios b/a and c/a, the cells the rays walked and updated, whether
        the three maps are equal cell for cell over (a), and each map's held cells and state bytes.
memory  A growing map's state (``state_nbytes()``) against OctoMap's tree (``OcTree.memoryUsage()``) on the
        same scans at the same resolution, with no box on either side: every CARMEN log of the data
        directory (OctoMap gets each scan's beams at z = 0.025 m, no-returns free up to ``range_max``, as
        ``bench maps`` feeds it), the 3-D scene of ``bench fusion`` and the Ouster frames (below).
ouster  The three frames of an Ouster OS-1-128 in ``ouster/`` of the data directory (``../shared/data`` or
        the repository's ``tests/data``), at 0.1 m with ``range_max`` 30 m and every height, into one
        growing map: its held cells and state bytes against the service's default
        ``FUZZYRISK_MAX_MAP_CELLS``, and the cells of a fixed box over the same cells.
"""

from __future__ import annotations

import argparse
import gzip
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.config import Settings
from bench import _data, _logmaps, bench_fusion
from bench.bench_fusion import Clock
from fuzzyocc import FuzzyMap, GridSpec, LaserScan, LatticeSpec, PointCloud, SensorModel
from fuzzyocc.maps import Window

RESOLUTION = _logmaps.RESOLUTION
BATCH = 16  # scans per integrate call, as _logmaps.fuse and a streaming robot send them
WIDE_M = 400.0  # the side of box (b)
DEFAULT_LOGS = ("acapulco", "seattle")
OUSTER_RESOLUTION = 0.1
OUSTER_RANGE_MAX = 30.0
PARTS = ("speed", "memory", "ouster")
#: Part speed runs a log's maps at least this many seconds each in all (more rounds for a short log, at most
#: ``MAX_ROUNDS``): a run of a third of a second is at the mercy of any burst of other work, and with 3 rounds
#: of 1-3 s the best CPU time of one map still moved by 10 % from one run of the bench to the next.
MIN_SECONDS = 8.0
MAX_ROUNDS = 25


@dataclass
class Fused:
    """One fusion of a log's scans into one map: its times and what it walked and holds."""

    wall_s: float
    cpu_s: float
    walked: int  # cells_traversed: cell visits of the rays, before the per-scan dedupe
    updated: int  # cells_updated: (scan, cell) pairs given evidence
    held: int
    state: int


def box_around(bounds: Window, side: float = WIDE_M) -> GridSpec | None:
    """A ``side`` x ``side`` m box centred on ``bounds``, its corner on the map's lattice (so its cells are the
    growing map's); None where ``bounds`` is wider than that."""
    res = bounds.resolution
    n = round(side / res)
    if any(s > n for s in bounds.shape):
        return None
    lo = [lo_ - (n - s) // 2 for lo_, s in zip(bounds.lo, bounds.shape)]
    origin = tuple(b + i * res for b, i in zip(bounds.lower, lo))
    # max_cells with room: GridSpec first counts cells as floats (size / resolution)
    return GridSpec(origin=origin, size=(n * res,) * len(lo), resolution=res, max_cells=2 * n ** len(lo))


def own_box(bounds: Window) -> GridSpec:
    """The box of ``bounds`` with its corner exactly on the growing map's lattice (``lower + lo * resolution``).

    Not ``Window.spec()``, which writes the corner as a person would (-86.85, not -86.85000000000001): a box
    whose corner is off the lattice by 1e-14 m rounds a few ray steps the other way, and on csail one cell
    of 15 M then differed from the growing map's (risk 0.0340 against 0.0333)."""
    res = bounds.resolution
    return GridSpec(origin=bounds.origin, size=tuple(n * res for n in bounds.shape), resolution=res,
                    max_cells=2 * math.prod(bounds.shape))  # room: GridSpec first counts cells as floats


def fuse(m: FuzzyMap, scans: list[LaserScan]) -> Fused:
    """Fuse ``scans`` into ``m`` in batches of ``BATCH``, timed."""
    walked = updated = 0
    with Clock() as clock:
        for k in range(0, len(scans), BATCH):
            stats = m.integrate_batch(scans[k : k + BATCH])
            walked += stats.cells_traversed
            updated += stats.cells_updated
    return Fused(clock.wall, clock.cpu, walked, updated, m.held_cells(), m.state_nbytes())


def same_cells(m: FuzzyMap, reference: FuzzyMap, bounds: Window) -> bool:
    """Whether ``m``'s risk and observed cells over ``bounds`` (lattice cells of ``reference``) are
    ``reference``'s."""
    half = 0.5 * bounds.resolution
    window = m.window([o + half for o in bounds.origin], [u - half for u in bounds.upper])
    ref = reference.window([o + half for o in bounds.origin], [u - half for u in bounds.upper])
    return (window is not None and ref is not None and window.shape == ref.shape == bounds.shape
            and np.array_equal(m.risk(window), reference.risk(ref))
            and np.array_equal(m.observed(window), reference.observed(ref)))


def _growing(ndim: int, resolution: float = RESOLUTION, sensor: SensorModel | None = None) -> FuzzyMap:
    return FuzzyMap(LatticeSpec(ndim, resolution), sensor)


def _mb(n: float) -> str:
    return f"{n / 1e6:,.1f} MB"


def speed(name: str, scans: list[LaserScan], rounds: int) -> FuzzyMap:
    """Part *speed* on one log; returns its growing map (for part *memory*)."""
    first = _growing(2)
    once = fuse(first, scans)  # compiles what the warm-up did not, and gives the bounds
    rounds = min(max(rounds, math.ceil(MIN_SECONDS / once.wall_s)), max(rounds, MAX_ROUNDS))
    bounds = first.bounds()
    assert bounds is not None
    del first
    specs: dict[str, Callable[[], FuzzyMap]] = {"(a) own box": lambda: FuzzyMap(own_box(bounds), SensorModel())}
    wide = box_around(bounds)
    if wide is not None:
        specs["(b) 400 x 400 m"] = lambda: FuzzyMap(wide, SensorModel())
    specs["(c) growing"] = lambda: _growing(2)
    labels = list(specs)
    runs: dict[str, list[Fused]] = {label: [] for label in labels}
    last: dict[str, FuzzyMap] = {}
    for r in range(rounds):
        for label in labels[r % len(labels):] + labels[: r % len(labels)]:
            last.pop(label, None)  # one map of a kind at a time
            m = specs[label]()
            runs[label].append(fuse(m, scans))
            last[label] = m
    best = {label: min(rs, key=lambda x: x.wall_s) for label, rs in runs.items()}
    cpu = {label: min(x.cpu_s for x in rs) for label, rs in runs.items()}
    a = best["(a) own box"]
    print(f"\n{name}: {len(scans)} scans of {scans[0].ranges.size} beams (range_max {scans[0].range_max:.1f} m), "
          f"{rounds} rounds; "
          f"growing bounds {bounds.shape[0]} x {bounds.shape[1]} cells = "
          f"{bounds.shape[0] * RESOLUTION:.1f} x {bounds.shape[1] * RESOLUTION:.1f} m from "
          f"({', '.join(f'{v:.2f}' for v in bounds.origin)})")
    if wide is None:
        print(f"  (b) skipped: the bounds are wider than {WIDE_M:.0f} m")
    print(f"  {'map':16s} {'box cells':>12s} {'wall s':>7s} {'cpu s':>7s} {'scans/s':>8s} {'vs (a)':>7s} "
          f"{'by cpu s':>8s} {'cells walked':>13s} {'cells updated':>13s} {'held cells':>11s} {'state':>9s} "
          f"{'same cells':>10s}")
    for label, f in best.items():
        m = last[label]
        box = f"{m.spec.num_cells:,}" if isinstance(m.spec, GridSpec) else "-"
        same = "(ref)" if label == "(a) own box" else ("yes" if same_cells(m, last["(a) own box"], bounds) else "NO")
        print(f"  {label:16s} {box:>12s} {f.wall_s:7.2f} {cpu[label]:7.2f} {len(scans) / f.wall_s:8.1f} "
              f"{a.wall_s / f.wall_s:6.2f}x {cpu['(a) own box'] / cpu[label]:7.2f}x {f.walked:13,} {f.updated:13,} "
              f"{f.held:11,} {_mb(f.state):>9s} {same:>10s}")
    walked = {f.walked for f in best.values()}
    if len(walked) > 1:
        spread = max(walked) - min(walked)
        print(f"  cells walked differ by {spread:,} ({spread / min(walked) * 1e6:.1f} ppm): a sensor on a cell face "
              "starts its rays in the cell below or above as (x - origin) / resolution rounds; the cells updated "
              "and the maps are the same")
    return last["(c) growing"]


def octomap_nbytes_of_log(scans: list[LaserScan]) -> tuple[int, float]:
    """OctoMap's tree of ``scans`` with no box (``_logmaps.insert_scan``: no-returns free up to ``range_max``):
    its ``memoryUsage()`` and the seconds it took."""
    import octomap  # the bench extra: octomap-python

    tree = octomap.OcTree(RESOLUTION)
    z = 0.5 * RESOLUTION  # the centre of the lattice's cell [0, res) in z
    with Clock() as clock:
        for s in scans:
            _logmaps.insert_scan(tree, s, z, math.inf)
    return int(tree.memoryUsage()), clock.wall


def octomap_of_clouds(clouds: list[PointCloud], resolution: float):  # type: ignore[no-untyped-def]
    """OctoMap's tree of 3-D ``clouds`` (``insertPointCloud`` each, in order, their ``range_max``), with the time it
    took."""
    import octomap

    tree = octomap.OcTree(resolution)
    with Clock() as clock:
        for c in clouds:
            tree.insertPointCloud(np.ascontiguousarray(c.points, dtype=np.float64),
                                  np.asarray(c.origin, dtype=np.float64), maxrange=c.range_max)
    return tree, clock


def octomap_nbytes_of_clouds(clouds: list[PointCloud], resolution: float) -> tuple[int, float]:
    """OctoMap's tree of 3-D ``clouds`` (:func:`octomap_of_clouds`): memory and seconds."""
    tree, clock = octomap_of_clouds(clouds, resolution)
    return int(tree.memoryUsage()), clock.wall


@dataclass(frozen=True)
class OusterFrame:
    """One Ouster frame as recorded: float32 rows ``x y z reflectivity`` in the sensor frame, rows at (0, 0, 0) (no
    return) dropped, and the sensor pose in the first frame's frame (a point in the map frame is ``R @ p + t``)."""

    rows: np.ndarray  # (N, 4) float32
    rotation: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,)


def ouster_frames(folder: Path) -> list[OusterFrame]:
    """The Ouster frames of ``folder``, in either layout: ``velodyne/NNNNNN.bin`` (``../shared/data/ouster``) or
    ``NNNNNN.bin.gz`` (``tests/data/ouster``), float32 rows ``x y z reflectivity`` in the sensor frame, beside
    ``poses.txt`` (KITTI: ``[R | t]`` a line)."""
    poses = np.loadtxt(folder / "poses.txt").reshape(-1, 3, 4)
    frames = []
    for i, pose in enumerate(poses):
        plain, packed = folder / "velodyne" / f"{i:06d}.bin", folder / f"{i:06d}.bin.gz"
        data = plain.read_bytes() if plain.is_file() else gzip.decompress(packed.read_bytes())
        rows = np.frombuffer(data, dtype=np.float32).reshape(-1, 4)
        frames.append(OusterFrame(rows[np.any(rows[:, :3] != 0.0, axis=1)], pose[:, :3], pose[:, 3]))
    return frames


def ouster_clouds(folder: Path) -> list[PointCloud]:
    """The Ouster frames of ``folder`` (:func:`ouster_frames`) as clouds in the first frame's frame, ``range_max``
    ``OUSTER_RANGE_MAX``."""
    clouds = []
    for frame in ouster_frames(folder):
        points = frame.rows[:, :3].astype(np.float64)
        clouds.append(PointCloud(points=points @ frame.rotation.T + frame.translation,
                                 origin=tuple(frame.translation), range_max=OUSTER_RANGE_MAX,
                                 max_rays=points.shape[0]))
    return clouds


def fuse_clouds(clouds: list[PointCloud], resolution: float) -> tuple[FuzzyMap, Clock]:
    """One growing 3-D map of ``clouds``, a cloud per integrate call, in order; with the time it took."""
    m = _growing(3, resolution)
    with Clock() as clock:
        for c in clouds:
            m.integrate_batch([c])
    return m, clock


def _memory_row(name: str, ours: FuzzyMap, ours_s: float | None, theirs: int, theirs_s: float) -> bool:
    ratio = ours.state_nbytes() / theirs
    print(f"  {name:20s} {ours.held_cells():12,} {_mb(ours.state_nbytes()):>10s} {_mb(theirs):>10s} {ratio:6.2f}x "
          f"{'yes' if ratio <= 1.0 else 'NO':>5s} {'-' if ours_s is None else f'{ours_s:.1f}':>8s} {theirs_s:8.1f}",
          flush=True)
    return ratio <= 1.0


def memory(maps: dict[str, FuzzyMap], ouster: tuple[list[PointCloud], FuzzyMap, float] | None) -> None:
    """Part *memory*: every log of the data directory (``maps`` holds those fused already), the 3-D scene, the
    Ouster frames."""
    print("\nmemory: a growing map's state_nbytes() against OctoMap's tree memoryUsage(), same scans, same "
          "resolution, no box on either side (target <= 1x); seconds: one fusion each (ours in batches of 16 scans, "
          "OctoMap a scan per insertPointCloud), for scale only")
    print(f"  {'scans':20s} {'held cells':>12s} {'ours':>10s} {'OctoMap':>10s} {'ratio':>7s} {'<= 1':>5s} "
          f"{'ours s':>8s} {'octo s':>8s}")
    met = total = 0
    for path in _logmaps.log_paths():
        name = _logmaps.log_name(path)
        scans = _logmaps.load(path)
        m, ours_s = maps.get(name), None
        if m is None:
            m = _growing(2)
            ours_s = fuse(m, scans).wall_s
        theirs, theirs_s = octomap_nbytes_of_log(scans)
        met, total = met + _memory_row(name, m, ours_s, theirs, theirs_s), total + 1
        maps.pop(name, None)
    rng = np.random.default_rng(7)  # bench fusion's scenes, in its order: its scene (b) is this one
    bench_fusion.planar_scene(rng, 30)
    scene = bench_fusion.lidar_scene(rng, 10)
    clouds = [PointCloud(points=p, origin=tuple(o), range_max=bench_fusion.RANGE_MAX_M)
              for p, o in zip(scene.points, scene.origins)]
    m = _growing(3, scene.spec.resolution, SensorModel(range_sigma=bench_fusion.RANGE_NOISE_M))  # as bench fusion's
    with Clock() as clock:
        for c in clouds:
            m.integrate_batch([c])
    theirs, theirs_s = octomap_nbytes_of_clouds(clouds, scene.spec.resolution)
    met, total = met + _memory_row("bench fusion (b) 3-D", m, clock.wall, theirs, theirs_s), total + 1
    if ouster is not None:
        clouds, m, ours_s = ouster
        theirs, theirs_s = octomap_nbytes_of_clouds(clouds, OUSTER_RESOLUTION)
        met, total = met + _memory_row("Ouster, 3 frames", m, ours_s, theirs, theirs_s), total + 1
    print(f"  state <= OctoMap's tree on {met} of {total}")


def ouster(clouds: list[PointCloud]) -> tuple[FuzzyMap, float]:
    """Part *ouster*: the frames in one growing map against the service's default map limit."""
    m, clock = fuse_clouds(clouds, OUSTER_RESOLUTION)
    seconds = clock.wall
    bounds = m.bounds()
    assert bounds is not None
    limit = Settings.model_fields["max_map_cells"].default
    box = math.prod(bounds.shape)
    print(f"\nouster: {len(clouds)} frames, {sum(c.points.shape[0] for c in clouds):,} returns, at "
          f"{OUSTER_RESOLUTION} m, range_max {OUSTER_RANGE_MAX:.0f} m, every height, in one growing map "
          f"({seconds:.1f} s)")
    print(f"  bounds {' x '.join(str(n) for n in bounds.shape)} cells = "
          f"{' x '.join(f'{n * OUSTER_RESOLUTION:.1f}' for n in bounds.shape)} m; a fixed box over them: {box:,} cells "
          f"= {box / limit:.2f}x the default FUZZYRISK_MAX_MAP_CELLS ({limit:,}): "
          f"{'refused' if box > limit else 'accepted'}")
    held = m.held_cells()
    print(f"  held cells {held:,} = {held / limit:.2f}x FUZZYRISK_MAX_MAP_CELLS: "
          f"{'fits' if held <= limit else 'DOES NOT FIT'}; state {_mb(m.state_nbytes())}, resident "
          f"{_mb(m.resident_nbytes())} (about {m.resident_nbytes() / held:.1f} B a held cell)")
    return m, seconds


def _warm_up() -> None:
    for m in (_growing(2), FuzzyMap(GridSpec(origin=(0.0, 0.0), size=(1.0, 1.0), resolution=RESOLUTION))):
        m.integrate_scan(pose=(0.5, 0.5, 0.0), angle_min=0.0, angle_increment=0.1, ranges=[0.3, np.inf, 0.4],
                         range_min=0.0, range_max=1.0)
        m.risk()
    _growing(3, 0.1).integrate_points(np.full((4, 3), 0.8), origin=(0.15, 0.15, 0.15), range_max=5.0)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--logs", default=",".join(DEFAULT_LOGS),
                        help="logs of part speed, comma-separated names (e.g. acapulco,seattle) or 'all'")
    parser.add_argument("--rounds", type=int, default=5, help="interleaved runs of each map in part speed; the "
                        "fastest is reported")
    parser.add_argument("--only", default=",".join(PARTS), help=f"parts to run, comma-separated: {', '.join(PARTS)}")
    _data.add_option(parser)
    args = parser.parse_args(argv)
    _data.use(args)
    parts = set(args.only.split(","))
    if not parts <= set(PARTS):
        parser.error(f"--only takes {', '.join(PARTS)}, got {args.only}")
    paths = {_logmaps.log_name(p): p for p in _logmaps.log_paths()}
    names = list(paths) if args.logs == "all" else args.logs.split(",")
    missing = [n for n in names if n not in paths]
    if missing:
        parser.error(f"--logs: no log {', '.join(missing)} in {_logmaps.log_dir()} (there: {', '.join(paths)})")
    ouster_dir = _data.needed("ouster") if "ouster" in parts else None  # before any work: a missing folder ends it
    t0 = time.perf_counter()
    _warm_up()
    print(f"numba warm-up: {time.perf_counter() - t0:.1f} s (excluded from the timings below)")
    print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}: wall times are shared with "
          "whatever else runs; cpu s (this process's CPU time) moves less with it")
    maps: dict[str, FuzzyMap] = {}
    if "speed" in parts:
        print(f"\nspeed: scans/s of the same scans in (a) the log's own box (the growing map's bounds), (b) a "
              f"{WIDE_M:.0f} x {WIDE_M:.0f} m box around it, (c) a growing map; the fastest of {args.rounds} "
              f"or more interleaved rounds (a short log gets up to {MAX_ROUNDS}: {MIN_SECONDS:.0f} s a map at least; "
              "wall s; cpu s: the least CPU time); targets b/a >= 0.9x and c/a >= 0.9x; cells walked: ray-cell "
              "visits before the per-scan dedupe; cells updated: (scan, cell) pairs given evidence")
        for name in names:
            maps[name] = speed(name, _logmaps.load(paths[name]), args.rounds)
    fused_ouster = None
    if ouster_dir is not None:
        clouds = ouster_clouds(ouster_dir)
        fused_ouster = (clouds, *ouster(clouds))
    if "memory" in parts:
        memory(maps, fused_ouster)
    print(f"\nload average at the end: {os.getloadavg()[0]:.1f}; {time.perf_counter() - t0:.0f} s in all")


if __name__ == "__main__":
    main()

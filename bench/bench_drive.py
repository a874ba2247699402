"""A long simulated 3-D drive into a growing map that forgets far space: its memory over time, and a plot.

    python -m bench.bench_drive [--minutes 30] [--every 3] [--rings 64] [--columns 128] [--forget-beyond 20]
                                [--plot bench/figures/drive_memory.png]          (from the repository root)

A robot drives at ``--speed`` (1.5 m/s) down a street that winds for ever (its centre line ``y = 6 sin(2 pi x /
240)`` m), generated in 20 m tiles from ``--seed``: buildings 4-20 m high on both sides with alleys between
them, parked cars and poles along the kerbs, the ground at z = 0. A lidar 1.8 m above the ground (an Ouster
OS1 pattern: ``--rings`` x ``--columns`` beams over +-16.6 degrees of elevation) sweeps every ``--every``
simulated seconds; ranges get 3 cm of Gaussian noise, beams that hit nothing are dropped (a lidar reports no
return), hits beyond ``range_max`` (30 m) are cut there by the map as no-returns. Each sweep is one integrate
call into a growing 3-D map at 0.1 m with ``forget_beyond`` ``--forget-beyond`` m.

Prints, every simulated minute, the map's held cells, state and resident bytes and the minute's fusion rate;
the peer, measured in the same run, is the same drive into a map that does not forget, over its first
``--peer-minutes`` (1: it grows by hundreds of MB a minute). Target: memory flat after the first minutes, the
largest state from minute ``2 x --settle`` (10) to the end at most 1.1x the largest of the first ``--settle``
(5) minutes; also printed, the ratio to the one sample at minute 5 and the state's fitted slope. Writes a PNG
of held cells and state over time (``--plot``).

A real drive sweeps at 10 Hz with 64 x 1024 beams. The defaults (8,192 beams every 3 s, a sweep every 4.5 m:
600 sweeps) keep a 30-minute drive to about 3.5 minutes of CPU on a 2-core machine: a sweep of 8,192 beams
costs about 0.35 s with its ray casting, a good part of it dropping the forgotten blocks one by one. What
the map holds is set by the distance it keeps and by how densely the beams cover it, not by how often it is
swept.
"""

from __future__ import annotations

import argparse
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bench.bench_fusion import RANGE_NOISE_M, Clock, _ray_boxes
from fuzzyocc import FuzzyMap, LatticeSpec, PointCloud, SensorModel

ROOT = Path(__file__).resolve().parents[1]
RESOLUTION = 0.1
RANGE_MAX_M = 30.0
SENSOR_HEIGHT_M = 1.8
TILE_M = 20.0  # the street is generated in tiles this long along x
STREET_HALF_M = 9.0  # centre line to the building fronts
AMPLITUDE_M, WAVELENGTH_M = 6.0, 240.0  # the centre line's winding
FLAT_WITHIN = 1.1  # the target: the state after the first minutes at most this multiple of minute --settle's


def centre_y(x: np.ndarray | float) -> np.ndarray | float:
    """The street's centre line, where the robot drives."""
    return AMPLITUDE_M * np.sin(2 * np.pi * np.asarray(x) / WAVELENGTH_M)


def tile_boxes(seed: int, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The boxes (lo, hi: (M, 3)) of tile ``k`` (x in ``[k * TILE_M, (k + 1) * TILE_M)``): the same for the same
    ``seed`` and ``k``, whenever it is asked for."""
    rng = np.random.default_rng([seed, k + (1 << 32)])  # k may be negative
    x0 = k * TILE_M
    c = float(centre_y(x0 + TILE_M / 2))
    lo, hi = [[x0, c - 45.0, -0.3]], [[x0 + TILE_M, c + 45.0, 0.0]]  # the ground
    for side in (-1.0, 1.0):
        x = x0 + rng.uniform(0.0, 3.0)
        while x < x0 + TILE_M - 2.0:  # buildings, alleys between them
            length = min(rng.uniform(5.0, 14.0), x0 + TILE_M - x)
            front = STREET_HALF_M + rng.uniform(0.0, 2.0)
            depth = rng.uniform(8.0, 15.0)
            y_near, y_far = c + side * front, c + side * (front + depth)
            lo.append([x, min(y_near, y_far), 0.0])
            hi.append([x + length, max(y_near, y_far), rng.uniform(4.0, 20.0)])
            x += length + rng.uniform(1.5, 5.0)
        for _ in range(rng.integers(0, 3)):  # parked cars along the kerb
            x = x0 + rng.uniform(0.0, TILE_M - 4.2)
            y = c + side * rng.uniform(5.6, 6.6)
            lo.append([x, y - 0.9, 0.15])
            hi.append([x + 4.2, y + 0.9, 1.5])
        for _ in range(rng.integers(0, 3)):  # poles
            x, y = x0 + rng.uniform(0.0, TILE_M), c + side * 7.8
            lo.append([x - 0.15, y - 0.15, 0.0])
            hi.append([x + 0.15, y + 0.15, 5.0])
    return np.array(lo), np.array(hi)


@dataclass
class Street:
    """The tiles of a street, made when first needed and kept while near the robot."""

    seed: int
    tiles: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)

    def boxes_near(self, x: float, reach: float) -> tuple[np.ndarray, np.ndarray]:
        first, last = math.floor((x - reach) / TILE_M), math.floor((x + reach) / TILE_M)
        for k in [k for k in self.tiles if not first <= k <= last]:
            del self.tiles[k]
        for k in range(first, last + 1):
            if k not in self.tiles:
                self.tiles[k] = tile_boxes(self.seed, k)
        parts = [self.tiles[k] for k in range(first, last + 1)]
        return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


def beam_directions(rings: int, columns: int) -> np.ndarray:
    """Unit directions (rings * columns, 3) of an Ouster OS1 pattern in the sensor frame."""
    elevation = np.radians(np.linspace(-16.6, 16.6, rings))
    azimuth = np.linspace(0.0, 2 * np.pi, columns, endpoint=False)
    el, az = np.meshgrid(elevation, azimuth, indexing="ij")
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1).reshape(-1, 3)


def sweep(street: Street, rng: np.random.Generator, t: float, speed: float, beams: np.ndarray) -> PointCloud:
    """The sweep at time ``t`` (seconds): the robot at ``x = speed * t`` on the centre line, heading along it."""
    x = speed * t
    y = float(centre_y(x))
    yaw = math.atan(AMPLITUDE_M * 2 * np.pi / WAVELENGTH_M * math.cos(2 * np.pi * x / WAVELENGTH_M))
    origin = np.array([x, y, SENSOR_HEIGHT_M])
    rot = np.array([[math.cos(yaw), -math.sin(yaw), 0.0], [math.sin(yaw), math.cos(yaw), 0.0], [0.0, 0.0, 1.0]])
    dirs = beams @ rot.T
    lo, hi = street.boxes_near(x, 2 * RANGE_MAX_M)
    r = np.concatenate([_ray_boxes(origin, d, lo, hi) for d in np.array_split(dirs, 16)])
    hit = np.isfinite(r)  # the sky gives no return
    r = r[hit] + rng.normal(0.0, RANGE_NOISE_M, int(hit.sum()))
    return PointCloud(points=origin + dirs[hit] * r[:, None], origin=tuple(origin), range_max=RANGE_MAX_M,
                      max_rays=beams.shape[0])


@dataclass
class Sample:
    t_s: float  # simulated time of the sweep
    held: int
    state: int
    resident: int


@dataclass(frozen=True)
class Flatness:
    """The verdict on a drive's memory: the largest state of its first minutes against the largest after them."""

    first: Sample  # the largest state over minutes (0, settle]
    at_settle: Sample  # the sample at minute ``settle``
    later: Sample  # the largest state from minute ``2 x settle`` on
    slope_mb_per_min: float  # least-squares slope of the state from minute ``2 x settle`` on

    @property
    def ratio(self) -> float:
        """The largest state after the first minutes over the largest of them (target <= ``FLAT_WITHIN``)."""
        return self.later.state / self.first.state

    @property
    def ratio_to_settle(self) -> float:
        """The largest state after the first minutes over the one sample at minute ``settle``."""
        return self.later.state / self.at_settle.state


def flat_verdict(samples: list[Sample], settle_min: float) -> Flatness:
    """How ``samples`` (in time order) end against their first ``settle_min`` minutes.

    The reference is the largest state of the first minutes, not the one sample at minute ``settle_min``: a
    sweep's state moves by about +-8 % with what the street holds around the robot, so one sample judges the
    street as much as the memory."""
    first = [s for s in samples if 0.0 < s.t_s <= 60.0 * settle_min]
    later = [s for s in samples if s.t_s >= 120.0 * settle_min]
    if not first or len(later) < 2:
        raise ValueError(f"the drive must be longer than {2 * settle_min:g} minutes to judge it")
    slope = np.polyfit([s.t_s / 60.0 for s in later], [s.state / 1e6 for s in later], 1)[0]
    return Flatness(first=max(first, key=lambda s: s.state), at_settle=first[-1],
                    later=max(later, key=lambda s: s.state), slope_mb_per_min=float(slope))


def plot(path: Path, samples: list[Sample], peer: list[Sample], settle_min: float, flat: Flatness,
         title: str) -> None:
    """Held cells (with the peer's) above, the forgetting map's state below, against simulated minutes."""
    import matplotlib  # the plots extra

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_cells, ax_bytes) = plt.subplots(2, 1, figsize=(9, 6.5), sharex=True)
    minutes = np.array([s.t_s for s in samples]) / 60.0
    ax_cells.plot(minutes, [s.held / 1e6 for s in samples], lw=1.0, label="forget_beyond")
    if peer:
        ax_cells.plot(np.array([s.t_s for s in peer]) / 60.0, [s.held / 1e6 for s in peer], lw=1.2, ls="--",
                      label="no forgetting (peer)")
    ax_cells.set_ylabel("held cells (millions)")
    ax_cells.legend(loc="upper right", fontsize=8)
    state = np.array([s.state for s in samples]) / 1e6
    ax_bytes.plot(minutes, state, lw=1.0, label="state_nbytes(), forget_beyond")
    ax_bytes.axhline(FLAT_WITHIN * flat.first.state / 1e6, color="tab:red", lw=0.8, ls=":",
                     label=f"{FLAT_WITHIN}x the largest of minutes 0-{settle_min:g}")
    ax_bytes.plot(flat.later.t_s / 60.0, flat.later.state / 1e6, "v", color="tab:red", ms=5,
                  label=f"largest from minute {2 * settle_min:g}: {flat.ratio:.2f}x")
    ax_bytes.set_ylim(0, 1.4 * state.max())
    ax_bytes.set_ylabel("state (MB)")
    ax_bytes.set_xlabel("simulated minutes")
    ax_bytes.legend(loc="lower right", fontsize=8)
    for ax in (ax_cells, ax_bytes):
        ax.set_ylim(bottom=0)
        ax.axvline(settle_min, color="grey", lw=0.6)
        ax.axvline(2 * settle_min, color="grey", lw=0.6)
        ax.grid(alpha=0.3)
    ax_cells.set_title(title, fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=30.0, help="simulated minutes of driving")
    parser.add_argument("--every", type=float, default=3.0, help="simulated seconds between sweeps")
    parser.add_argument("--rings", type=int, default=64)
    parser.add_argument("--columns", type=int, default=128)
    parser.add_argument("--speed", type=float, default=1.5, help="m/s")
    parser.add_argument("--forget-beyond", type=float, default=20.0, help="the map's forget_beyond, metres")
    parser.add_argument("--settle", type=float, default=5.0, help="minutes after which memory must be flat")
    parser.add_argument("--peer-minutes", type=float, default=1.0,
                        help="minutes of the same drive into a map without forgetting (the peer)")
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--plot", type=Path, default=ROOT / "bench" / "figures" / "drive_memory.png")
    args = parser.parse_args(argv)
    if args.minutes <= 2 * args.settle:
        parser.error(f"--minutes must exceed 2 x --settle ({2 * args.settle:g})")
    sensor = SensorModel(range_sigma=RANGE_NOISE_M)
    forgetting = FuzzyMap(LatticeSpec(3, RESOLUTION), sensor)
    forgetting.forget_beyond = args.forget_beyond
    keeping: FuzzyMap | None = FuzzyMap(LatticeSpec(3, RESOLUTION), sensor)
    beams = beam_directions(args.rings, args.columns)
    street, rng = Street(args.seed), np.random.default_rng(args.seed)
    n_sweeps = int(round(args.minutes * 60.0 / args.every))
    per_minute = max(1, round(60.0 / args.every))
    t0 = time.perf_counter()
    warm = FuzzyMap(LatticeSpec(3, RESOLUTION), sensor)  # compiles the kernels before the clock runs
    warm.forget_beyond = args.forget_beyond
    warm.integrate_batch([sweep(street, np.random.default_rng(0), 0.0, args.speed, beams)])
    del warm
    print(f"numba warm-up: {time.perf_counter() - t0:.1f} s (excluded)")
    print(f"{args.minutes:g} simulated minutes at {args.speed} m/s ({args.minutes * 60 * args.speed / 1000:.1f} km), "
          f"a sweep of {beams.shape[0]:,} beams every {args.every:g} s ({n_sweeps:,} sweeps), {RESOLUTION} m, "
          f"range_max {RANGE_MAX_M:.0f} m, forget_beyond {args.forget_beyond:g} m; peer: no forgetting, first "
          f"{args.peer_minutes:g} minutes; machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}")
    print(f"  {'minute':>6s} {'held cells':>12s} {'state MB':>9s} {'resident MB':>11s} {'fused/s':>8s} "
          f"{'rays/s':>9s} {'peer held':>12s} {'peer state MB':>13s}")
    samples: list[Sample] = []
    peer: list[Sample] = []
    fusion_s = rays = 0.0
    minute_rates: list[float] = []
    started = time.perf_counter()
    for i in range(n_sweeps):
        t = i * args.every
        cloud = sweep(street, rng, t, args.speed, beams)
        with Clock() as clock:
            forgetting.integrate_batch([cloud])
        fusion_s += clock.wall
        rays += cloud.points.shape[0]
        samples.append(Sample(t, forgetting.held_cells(), forgetting.state_nbytes(), forgetting.resident_nbytes()))
        p = None
        if keeping is not None and t < 60.0 * args.peer_minutes:
            keeping.integrate_batch([cloud])
            p = Sample(t, keeping.held_cells(), keeping.state_nbytes(), keeping.resident_nbytes())
            peer.append(p)
        else:
            keeping = None  # its minutes are over: let its memory go
        if (i + 1) % per_minute == 0 or i + 1 == n_sweeps:
            s = samples[-1]
            minute_rates.append(per_minute / fusion_s)
            print(f"  {(t + args.every) / 60:6.1f} {s.held:12,} {s.state / 1e6:9.1f} {s.resident / 1e6:11.1f} "
                  f"{minute_rates[-1]:8.2f} {rays / fusion_s:9,.0f} "
                  f"{(f'{p.held:,}' if p else '-'):>12s} {(f'{p.state / 1e6:.1f}' if p else '-'):>13s}", flush=True)
            fusion_s = rays = 0.0
    flat = flat_verdict(samples, args.settle)
    print(f"\nstate, largest of minutes 0-{args.settle:g}: {flat.first.state / 1e6:.1f} MB at minute "
          f"{flat.first.t_s / 60:.1f}; largest from minute {2 * args.settle:g} to {args.minutes:g}: "
          f"{flat.later.state / 1e6:.1f} MB at minute {flat.later.t_s / 60:.1f} = {flat.ratio:.3f}x (target <= "
          f"{FLAT_WITHIN}x): {'flat' if flat.ratio <= FLAT_WITHIN else 'NOT FLAT'}")
    print(f"  against the one sample at minute {flat.at_settle.t_s / 60:.1f} ({flat.at_settle.state / 1e6:.1f} MB): "
          f"{flat.ratio_to_settle:.3f}x; fitted slope from minute {2 * args.settle:g}: "
          f"{flat.slope_mb_per_min:+.3f} MB/min")
    if peer:
        last = peer[-1]
        mine = next(s for s in samples if s.t_s == last.t_s)
        print(f"peer without forgetting at minute {last.t_s / 60:.1f}: {last.state / 1e6:.1f} MB ({last.held:,} held "
              f"cells) = {last.state / mine.state:.2f}x the forgetting map's at that sweep, and growing")
    bounds = forgetting.bounds()
    if bounds is not None:
        print(f"the map's bounds at the end: {' x '.join(f'{n * RESOLUTION:.1f}' for n in bounds.shape)} m "
              f"(2 x forget_beyond = {2 * args.forget_beyond:g} m across)")
    thirds = [p for p in np.array_split(np.array(minute_rates), 3) if p.size]
    print(f"sweeps fused a second, median of each third of the minutes: "
          f"{' / '.join(f'{np.median(p):.2f}' for p in thirds)} (wall time: the machine's other work moves it)")
    title = (f"{args.minutes:g} min at {args.speed} m/s, {beams.shape[0]:,} beams every {args.every:g} s, "
             f"{RESOLUTION} m, range_max {RANGE_MAX_M:.0f} m, forget_beyond {args.forget_beyond:g} m")
    plot(args.plot, samples, peer, args.settle, flat, title)
    print(f"plot: {args.plot}; {time.perf_counter() - started:.0f} s of driving, load average "
          f"{os.getloadavg()[0]:.1f} at the end")


if __name__ == "__main__":
    main()

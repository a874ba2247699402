"""Growing maps through the service: what a box costs over HTTP, and a growing map against the fixed map of its bounds.

    python -m bench.bench_growing [--logs seattle,acapulco] [--batch 10] [--rounds 2]
                                  [--corridor-batch 64] [--every N] [--repeats 2] [--data DIR]
                                                                                    (from the repository root)

One ``python -m app`` on loopback (``bench._client.ServerProcess``: a temporary data directory, every limit at its
default), one client posting a CARMEN log's scans in log order as JSON batches (``app.cli.import_log.scan_json``,
what ``python -m app.import_log --url`` posts), 0.05 m cells.

1. **A box's cost.** Each log of ``--logs`` goes first into a growing map (a warm-up, and its ``bounds``), then,
   ``--rounds`` times, into (a) a fixed map whose box is those bounds, (b) a fixed 400 x 400 m box (64 M cells)
   centred on them and (c) a growing map, batch by batch in turn (each map gets the log's batches of ``--batch``
   scans in order; the three share whatever load the machine has). The boxes' corners lie on the growing map's
   lattice, so the three walk the same cells: the last round's are compared (b through a window of the bounds).
   Prints scans/s (each map's scans over the seconds of its own requests), b/a and c/a (target >= 0.9x: fusion
   costs what the rays cost, not what the box holds) and each map's ``held_cells``.
2. **infinite-corridor, whole.** Every ``--every``-th scan in batches of ``--corridor-batch`` into a growing map,
   then into a fixed map of its bounds (origin and size from ``GET /maps/{name}``). (i) Every cell of the two
   ``risk.npy`` (and ``layer=observed``) compared bit for bit. (ii) ``risk.npy`` and ``risk.png`` of the bounds,
   best of ``--repeats`` each, alternating maps; ratio growing / fixed (target <= 1.1x: no slower, noise allowed).
   (iii) A grid plan between the two poses of the log farthest apart (every 5th pose), same seed on both, with
   the defaults otherwise (``allow_unknown``: the search crosses never-observed space). A fixed map's worker
   keeps a version's grid and its footprint field for the next plan on that version, a growing map's plan ships
   its grid each time, so each rep first moves both maps to a new version (a clear of a never-observed cell,
   which changes no cell) and times the first plan on it, then the same plan again. Ratio growing / fixed of
   each (target <= 1.1x). ``time_limit`` is 10 s: the grid search is not bounded by it, but the service gives a
   plan up 20 s after its clock bound (3 x ``time_limit`` when seeded), and this search of 31 M cells took
   6.5-9 s in a worker, up to 21 s in-process on a loaded 2-core machine.

Reads and plans of more than 4 M cells take turns in the service's big-reads lane, which rests ``1 / share - 1``
times a read's duration after it (``FUZZYRISK_HEAVY_READ_SHARE``); every timed request here is followed by that rest
after it, so a time is the request's own. **Time**: 5-7 minutes on a loaded 2-core machine (PNGs of 31 M cells and
their rests, the plans, the posting).
"""

from __future__ import annotations

import argparse
import io
import json
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import httpx
import numpy as np

from app.cli.import_log import scan_json
from app.config import Settings
from bench import _data
from bench._client import ServerProcess, machine
from bench._logmaps import log_dir
from fuzzyocc import LaserScan
from fuzzyocc.carmen import read_carmen

RESOLUTION = 0.05
BIG_BOX_M = 400.0
CORRIDOR = "infinite-corridor"
#: after a big read the lane rests this many times the read's duration (the service's default share)
LANE_REST = 1.0 / Settings.model_fields["heavy_read_share"].default - 1.0
TARGET_RATE = 0.9  # scans/s in a bigger box or a growing map, at least this share of the log's own box's
TARGET_SLOWER = 1.1  # a growing map's read or plan at most this multiple of the fixed map's (noise allowed)


class Refused(RuntimeError):
    """A request the service did not answer with 2xx: the request and the answer, as they were."""

    def __init__(self, method: str, path: str, sent: str, response: httpx.Response) -> None:
        self.status = response.status_code
        super().__init__(f"{method} {path} {sent} -> {response.status_code} {response.text[:600]}")


class Service:
    """The calls of this bench to one server, each checked (``Refused`` on anything but 2xx)."""

    def __init__(self, url: str) -> None:
        self.http = httpx.Client(base_url=url, timeout=300.0)

    def close(self) -> None:
        self.http.close()

    def call(self, method: str, path: str, *, body: dict[str, Any] | None = None, content: bytes | None = None,
             params: dict[str, str] | None = None) -> httpx.Response:
        headers = {"content-type": "application/json"} if content is not None else None
        response = self.http.request(method, path, json=body, content=content, params=params, headers=headers)
        if response.status_code >= 300:
            sent = json.dumps(body) if body is not None else f"({len(content)} bytes)" if content else ""
            raise Refused(method, path + (f"?{httpx.QueryParams(params)}" if params else ""), sent, response)
        return response

    def create(self, body: dict[str, Any]) -> dict[str, Any]:
        return dict(self.call("POST", "/maps", body=body).json())

    def info(self, name: str) -> dict[str, Any]:
        return dict(self.call("GET", f"/maps/{name}").json())

    def delete(self, name: str) -> None:
        self.call("DELETE", f"/maps/{name}")

    def post_scans(self, name: str, bodies: Sequence[bytes], scans: int) -> float:
        """Post every batch in order, one at a time; seconds from the first request to the last answer."""
        fused = 0
        started = time.perf_counter()
        for body in bodies:
            fused += int(self.call("POST", f"/maps/{name}/scans", content=body).json()["scans_fused"])
        elapsed = time.perf_counter() - started
        if fused != scans:
            raise RuntimeError(f"{name}: {fused} scans fused of {scans} posted")
        return elapsed

    def grid(self, name: str, layer: str = "risk", params: dict[str, str] | None = None
             ) -> tuple[np.ndarray, tuple[str, str]]:
        """A ``risk.npy`` layer and its (``X-Map-Origin``, ``X-Map-Shape``)."""
        response = self.call("GET", f"/maps/{name}/risk.npy", params={"layer": layer, **(params or {})})
        where = (response.headers["x-map-origin"], response.headers["x-map-shape"])
        return np.load(io.BytesIO(response.content), allow_pickle=False), where

    def timed(self, method: str, path: str, *, copy_bound: float = math.inf, **kwargs: Any
              ) -> tuple[float, httpx.Response]:
        """One request's seconds (the whole answer read); then the big-reads lane's rest after it is waited out, so
        that the next request's time is its own. The lane holds a read for all of it, a plan for its grid's copy,
        which takes at most ``copy_bound`` seconds."""
        started = time.perf_counter()
        response = self.call(method, path, **kwargs)
        elapsed = time.perf_counter() - started
        time.sleep(LANE_REST * min(elapsed, copy_bound) + 0.05)
        return elapsed, response


@dataclass(frozen=True)
class Log:
    name: str
    scans: list[LaserScan]

    @classmethod
    def read(cls, name: str, every: int = 1) -> Log:
        path = log_dir() / f"{name}-corrected.log.gz"
        if not path.exists():
            raise SystemExit(f"{path} is missing: {_data.describe()}")
        return cls(name, read_carmen(path)[::every])

    def bodies(self, batch: int) -> list[bytes]:
        """``ScanBatch`` request bodies of ``batch`` scans, in log order."""
        return [json.dumps({"scans": [scan_json(s) for s in self.scans[i:i + batch]]}).encode()
                for i in range(0, len(self.scans), batch)]

    def far_pair(self) -> tuple[list[float], list[float]]:
        """The two sensor positions of the log farthest apart (every 5th scan's): free space, across the map."""
        xy = np.array([s.pose[:2] for s in self.scans[::5]])
        d = np.linalg.norm(xy[:, None, :] - xy[None, :, :], axis=-1)
        i, j = np.unravel_index(int(np.argmax(d)), d.shape)
        return xy[i].tolist(), xy[j].tolist()


def _lattice(value: float) -> float:
    """``value`` snapped to the growing lattice (a multiple of the resolution), written as the service writes a
    window's corner."""
    return float(f"{round(value / RESOLUTION) * RESOLUTION:.15g}")


def _mcells(n: float) -> str:
    return f"{n / 1e6:.2f} M"


def _verdict(ok: bool) -> str:
    return "met" if ok else "NOT MET"


def _differing(a: np.ndarray, b: np.ndarray) -> int:
    """Cells whose values differ bit for bit (-1: different shapes)."""
    if a.shape != b.shape or a.dtype != b.dtype:
        return -1
    view = {1: np.uint8, 4: np.uint32}[a.dtype.itemsize]
    return int(np.count_nonzero(a.view(view) != b.view(view)))


# ---------------------------------------------------------------- 1. a box's cost


def box_cost(service: Service, log: Log, batch: int, rounds: int) -> None:
    bodies = log.bodies(batch)
    beams = log.scans[0].ranges.size
    warm = f"{log.name}-bounds"
    service.create({"name": warm, "resolution": RESOLUTION})
    warm_s = service.post_scans(warm, bodies, len(log.scans))
    grown = service.info(warm)
    service.delete(warm)
    origin, size, shape = grown["origin"], grown["size"], grown["shape"]
    print(f"\n{log.name}: {len(log.scans)} scans of {beams} beams in batches of {batch}; a growing map's bounds "
          f"{shape[0]} x {shape[1]} cells ({size[0]:.2f} x {size[1]:.2f} m) from ({origin[0]:g}, {origin[1]:g}) "
          f"(warm-up: {len(log.scans) / warm_s:.1f} scans/s)", flush=True)
    centre = [o + s / 2 for o, s in zip(origin, size)]
    big_origin = [_lattice(c - BIG_BOX_M / 2) for c in centre]
    settings = {
        "a": {"origin": origin, "size": size},
        "b": {"origin": big_origin, "size": [BIG_BOX_M, BIG_BOX_M]},
        "c": {},
    }
    labels = {"a": "(a) fixed, the log's bounds", "b": f"(b) fixed, {BIG_BOX_M:g} x {BIG_BOX_M:g} m",
              "c": "(c) growing"}
    seconds: dict[str, list[float]] = {key: [] for key in settings}  # per round
    infos: dict[str, dict[str, Any]] = {}
    kept: dict[str, str] = {}
    for r in range(rounds):
        names = {key: f"{log.name}-{key}-{r}" for key in settings}
        for key, name in names.items():
            service.create({"name": name, "resolution": RESOLUTION, **settings[key]})
        # batch k goes to the three maps in turn (the order rotated), so that a shared machine's load falls on
        # each alike; each map gets the log's batches in order, one request at a time
        spent = dict.fromkeys(settings, 0.0)
        for k, body in enumerate(bodies):
            for key in list(settings)[k % 3:] + list(settings)[:k % 3]:
                spent[key] += service.post_scans(names[key], [body], len(log.scans[k * batch:(k + 1) * batch]))
        for key, name in names.items():
            seconds[key].append(spent[key])
            infos[key] = service.info(name)
            if r == rounds - 1:
                kept[key] = name
            else:
                service.delete(name)
    n = len(log.scans)
    rate = {key: n * rounds / sum(v) for key, v in seconds.items()}
    print(f"  {'map':<30} {'box cells':>10} {'held cells':>11}   scans/s: each round ({rounds}), all")
    for key, label in labels.items():
        box = "-" if infos[key]["extent"] == "growing" else _mcells(math.prod(infos[key]["shape"]))
        print(f"  {label:<30} {box:>10} {_mcells(infos[key]['held_cells']):>11}   "
              f"{' / '.join(f'{n / v:.1f}' for v in seconds[key])}, {rate[key]:.1f}")
    ba, ca = rate["b"] / rate["a"], rate["c"] / rate["a"]
    each = ", ".join(f"{seconds['a'][r] / seconds['b'][r]:.2f}x / {seconds['a'][r] / seconds['c'][r]:.2f}x"
                     for r in range(rounds))
    print(f"  b/a {ba:.2f}x, c/a {ca:.2f}x (each round: {each}; target >= {TARGET_RATE}x: "
          f"{_verdict(min(ba, ca) >= TARGET_RATE)})")
    bounds = infos["c"]["bounds"]
    window = {"min": ",".join(f"{v + RESOLUTION / 2:.15g}" for v in bounds["min"]),
              "max": ",".join(f"{v - RESOLUTION / 2:.15g}" for v in bounds["max"])}
    differing = []
    for layer in ("risk", "observed"):
        a, a_at = service.grid(kept["a"], layer)
        b, b_at = service.grid(kept["b"], layer, window)
        c, c_at = service.grid(kept["c"], layer)
        if not a_at == b_at == c_at:
            print(f"  {layer}: the grids lie apart: a {a_at}, b's window {b_at}, c {c_at}")
        differing.append((_differing(a, b), _differing(a, c)))
    same = all(n == 0 for pair in differing for n in pair)
    print(f"  cells equal (a, b's window of the bounds, c): {'yes' if same else 'no'} (differing a/b, a/c: risk "
          f"{differing[0][0]} / {differing[0][1]}, observed {differing[1][0]} / {differing[1][1]})", flush=True)
    for name in kept.values():
        service.delete(name)


# ---------------------------------------------------------------- 2. infinite-corridor, whole


def corridor(service: Service, log: Log, batch: int, every: int, repeats: int) -> None:
    bodies = log.bodies(batch)
    names = {"growing": "corridor-growing", "fixed": "corridor-fixed"}
    print(f"\n{log.name}: {len(log.scans)} scans" + (f" (every {every}th)" if every > 1 else "") +
          f" in batches of {batch}", flush=True)
    service.create({"name": names["growing"], "resolution": RESOLUTION})
    seconds = {"growing": service.post_scans(names["growing"], bodies, len(log.scans))}
    grown = service.info(names["growing"])
    fixed = service.create({"name": names["fixed"], "resolution": RESOLUTION, "origin": grown["origin"],
                            "size": grown["size"]})
    if fixed["shape"] != grown["shape"]:
        raise RuntimeError(f"the fixed map of the bounds has {fixed['shape']} cells, the bounds {grown['shape']}")
    seconds["fixed"] = service.post_scans(names["fixed"], bodies, len(log.scans))
    infos = {key: service.info(name) for key, name in names.items()}
    shape = grown["shape"]
    print(f"  bounds {shape[0]} x {shape[1]} cells ({_mcells(math.prod(shape))}) from ({grown['origin'][0]:g}, "
          f"{grown['origin'][1]:g}); held cells: growing {_mcells(infos['growing']['held_cells'])}, fixed "
          f"{_mcells(infos['fixed']['held_cells'])}; scans/s: growing {len(log.scans) / seconds['growing']:.1f}, "
          f"fixed {len(log.scans) / seconds['fixed']:.1f}")

    # (i) every cell
    differing = {}
    for layer in ("risk", "observed"):
        g, g_at = service.grid(names["growing"], layer)
        f, f_at = service.grid(names["fixed"], layer)
        if g_at != f_at:
            print(f"  {layer}: the answers lie apart: growing {g_at}, fixed {f_at}")
        differing[layer] = _differing(g, f)
        if layer == "observed":
            never = np.argwhere(~g)  # a never-observed cell of both, cleared below to move to a new version
    same = all(n == 0 for n in differing.values())
    print(f"  (i) cells equal: {'yes' if same else 'no'} (differing cells: risk {differing['risk']}, observed "
          f"{differing['observed']}; origin and shape {g_at})", flush=True)

    # (ii) reads of the bounds
    read_s = {}
    for fmt in ("npy", "png"):
        best = {key: math.inf for key in names}
        for rep in range(repeats):
            for key in (list(names) if rep % 2 == 0 else list(names)[::-1]):
                elapsed, response = service.timed("GET", f"/maps/{names[key]}/risk.{fmt}")
                best[key] = min(best[key], elapsed)
        read_s[fmt] = max(best.values())
        ratio = best["growing"] / best["fixed"]
        print(f"  (ii) risk.{fmt} of the bounds ({len(response.content) / 2**20:.1f} MiB), best of {repeats}: growing "
              f"{1000 * best['growing']:.0f} ms, fixed {1000 * best['fixed']:.0f} ms: {ratio:.2f}x "
              f"(target <= {TARGET_SLOWER}x: {_verdict(ratio <= TARGET_SLOWER)})", flush=True)

    # (iii) a grid plan across the map
    start, goal = log.far_pair()
    plan = {"start": start, "goal": goal, "planner": "grid", "seed": 7, "time_limit": 10.0}
    cell = [float(grown["origin"][a] + (never[0][a] + 0.5) * RESOLUTION) for a in range(2)]
    times: dict[tuple[str, str], list[float]] = {}
    worker: dict[tuple[str, str], list[float]] = {}
    answers: dict[str, dict[str, Any]] = {}
    print(f"  (iii) grid plan from ({start[0]:.2f}, {start[1]:.2f}) to ({goal[0]:.2f}, {goal[1]:.2f}), "
          f"{math.dist(start, goal):.1f} m apart, seed 7:", flush=True)
    try:
        for rep in range(repeats):
            for key in (list(names) if rep % 2 == 0 else list(names)[::-1]):
                service.call("POST", f"/maps/{names[key]}/clear", body={"min": cell, "max": cell})
                for when in ("first", "again"):
                    # a plan's copy of the grid takes less than a read of it as .npy (the copy and the encoding)
                    elapsed, response = service.timed("POST", f"/maps/{names[key]}/plan", body=plan,
                                                      copy_bound=read_s["npy"])
                    answers[key] = response.json()
                    times.setdefault((key, when), []).append(elapsed)
                    worker.setdefault((key, when), []).append(answers[key]["planning_time"])
    except Refused as exc:
        print(f"      refused: {exc}", flush=True)
        return
    for key, answer in answers.items():
        print(f"      {key}: {answer['status']}, {answer['length']:.1f} m, {len(answer['path'])} points")
    print(f"      same path on both: {'yes' if answers['growing']['path'] == answers['fixed']['path'] else 'no'}")
    for when, what in (("first", "first plan on a version"), ("again", "the same plan again")):
        g, f = min(times[("growing", when)]), min(times[("fixed", when)])
        gw, fw = min(worker[("growing", when)]), min(worker[("fixed", when)])
        print(f"      {what}, best of {repeats}: growing {1000 * g:.0f} ms (worker {1000 * gw:.0f}), fixed "
              f"{1000 * f:.0f} ms (worker {1000 * fw:.0f}): {g / f:.2f}x (target <= {TARGET_SLOWER}x: "
              f"{_verdict(g / f <= TARGET_SLOWER)})", flush=True)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--logs", default="seattle,acapulco", help="logs of part 1 (default seattle,acapulco)")
    parser.add_argument("--batch", type=int, default=10, help="scans per request in part 1 (default 10)")
    parser.add_argument("--rounds", type=int, default=2, help="rounds of the three maps in part 1 (default 2)")
    parser.add_argument("--corridor-batch", type=int, default=64, help="scans per request in part 2 (default 64)")
    parser.add_argument("--every", type=int, default=1, metavar="N",
                        help="part 2 takes every Nth scan of infinite-corridor (default 1: all)")
    parser.add_argument("--repeats", type=int, default=2, help="timed reads and plans per map in part 2 (default 2)")
    parser.add_argument("--skip", choices=("box", "corridor"), default=None, help="leave one part out")
    _data.add_option(parser)
    args = parser.parse_args(argv)
    _data.use(args)
    logs = [Log.read(name) for name in args.logs.split(",")] if args.skip != "box" else []
    corridor_log = Log.read(CORRIDOR, args.every) if args.skip != "corridor" else None
    print(f"machine: {machine()}")
    started = time.perf_counter()
    server = ServerProcess().start()
    service = Service(server.url)
    try:
        print(f"server: python -m app on {server.url}, every limit at its default "
              f"(FUZZYRISK_MAX_MAP_CELLS {Settings.model_fields['max_map_cells'].default:,})", flush=True)
        for log in logs:
            box_cost(service, log, args.batch, args.rounds)
        if corridor_log is not None:
            corridor(service, corridor_log, args.corridor_batch, args.every, args.repeats)
    except BaseException:
        print(f"server log, last lines:\n{server.log_tail()}")
        raise
    finally:
        service.close()
        server.close()
    print(f"\n{time.perf_counter() - started:.0f} s; load average {machine().rsplit(' ', 1)[-1]}")


if __name__ == "__main__":
    main()

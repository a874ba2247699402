"""``python -m app.import_log``: a map from a recorded CARMEN laser log, in-process or through the service.

    python -m app.import_log LOG [--resolution 0.05] [--margin 1] [--every N] [--max-range M]
                             [--model fuzzy|bayes] [--png FILE] [--nav2 FILE.zip] [--npy FILE]
                             [--url http://127.0.0.1:8000 --map NAME [--api-key KEY] [--append]]
    python -m app.import_log --trajectory FILE --url http://127.0.0.1:8000 --map NAME [--api-key KEY] [--no-wait]

The map's bounds are those of the log's poses and hits, padded by ``--margin`` (see
:func:`fuzzyocc.carmen.grid_for_scans`). Without ``--url`` the scans are fused here, into
``FuzzyMap(spec)`` (or ``BayesMap``), and the files are rendered by :mod:`app.formats.exports`, as the
service renders them. With ``--url`` the map is created on the service (with the same sensor
model) and the scans are posted in order as JSON batches, each with its log stamp as ``header.stamp``
(a log whose stamps do not increase has its scans numbered at 5 Hz, and the command says so:
:func:`fuzzyocc.carmen.log_stamps_ns`); the files are then downloaded.
Either way the scans are fused in log order, so a new map's risk is the same bit for bit.
Progress goes to stderr (``app.cli.progress``: a bar on a terminal, else a line every few seconds; a
first run says when it compiles the fusion kernels), a one-line summary to stdout; errors exit 1 with a message.

``--trajectory FILE`` corrects a map built from a log, after a SLAM loop closure: FILE is the corrected log, whose
scans' stamps (the rule of an import, :func:`~fuzzyocc.carmen.log_stamps_ns`) and laser poses make the
``nav_msgs/Path`` put on ``--map`` (``PUT /maps/{name}/trajectory``, :mod:`app.cli.trajectory`). The service
re-poses every stored scan whose stamp the path spans and rebuilds the map in the background; the command waits for
the rebuild (progress on stderr: the scans re-fused of the total) and says how many scans were re-posed and the map's
new version, or returns once the correction is held (``--no-wait``). A scan imported from the same log, or with
``--every``, has its stamp in the path, so it takes that pose exactly.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any
from urllib.parse import quote

import numpy as np

from app.cli.common import (
    ImportFailed,
    ServiceClient,
    add_output_options,
    add_service_options,
    compile_notice,
    create_map,
    download_outputs,
    import_main,
    name_taken,
    non_negative,
    positive,
    say_if_the_service_compiles,
    write_outputs,
)
from app.cli.progress import Progress
from app.cli.trajectory import map_frame, put_trajectory, sensor_path, wait_for_rebuild
from app.ops.version import add_version_option
from app.ros.messages_in import stamp_header
from fuzzyocc import BayesMap, FuzzyMap, GridSpec, LaserScan, LatticeSpec
from fuzzyocc.carmen import grid_for_scans, read_carmen

PROG = "fuzzyrisk-import-log"


# ---------------------------------------------------------------- what both paths share


@dataclasses.dataclass(frozen=True)
class BeamCounts:
    """Beams of the scans taken: hits, no-returns, and readings skipped as below ``range_min`` (a SICK's 0)."""

    hits: int
    no_returns: int
    skipped: int

    @classmethod
    def of(cls, scans: Sequence[LaserScan]) -> BeamCounts:
        hits = no_returns = skipped = 0
        for s in scans:
            valid = s.ranges >= s.range_min  # False for NaN too, as LaserScan.to_rays
            far = s.ranges >= s.range_max
            no_returns += int(np.count_nonzero(far))
            hits += int(np.count_nonzero(valid & ~far))
            skipped += int(s.ranges.size - np.count_nonzero(valid))
        return cls(hits, no_returns, skipped)


class FusionProgress:
    """The scans fused so far and their rays, shown as the stage ``fusing`` of the command's progress."""

    def __init__(self, total: int, progress: Progress) -> None:
        self.progress = progress
        self.scans = self.rays = 0
        progress.stage("fusing", total, "scans")

    def add(self, scans: int, rays: int) -> None:
        self.scans += scans
        self.rays += rays
        self.progress.update(self.scans, f"{self.rays:,} rays")


def _batches(scans: Sequence[LaserScan], size: int) -> list[Sequence[LaserScan]]:
    return [scans[i:i + size] for i in range(0, len(scans), size)]


# ---------------------------------------------------------------- in-process


def _in_process(args: argparse.Namespace, scans: Sequence[LaserScan], spec: GridSpec,
                progress: FusionProgress) -> str:
    """Fuse here and write the files; the summary's map part."""
    if args.growing:
        occupancy: FuzzyMap | BayesMap = FuzzyMap(LatticeSpec(2, spec.resolution))
    else:
        occupancy = FuzzyMap(spec) if args.model == "fuzzy" else BayesMap(spec)
    for batch in _batches(scans, args.batch):
        stats = occupancy.integrate_batch(batch)
        progress.add(stats.scans, stats.rays)
    bounds = occupancy.window()
    if bounds is not None:  # a growing map's files cover its bounds
        write_outputs(args, bounds.spec(), occupancy.risk(bounds), occupancy.observed(bounds), args.log.name)
    return f"{args.model} map in-process"


# ---------------------------------------------------------------- through the service


def scan_json(scan: LaserScan) -> dict[str, Any]:
    """A scan as ``POST /maps/{name}/scans`` takes it (a ``LaserScanIn``), its numbers exact."""
    x, y, theta = scan.pose
    # json writes the shortest repr that reads back to the same float64: the service fuses our numbers
    ranges = ["inf" if math.isinf(r) else r for r in scan.ranges.tolist()]
    return {"pose": {"x": x, "y": y, "theta": theta}, "angle_min": scan.angle_min,
            "angle_increment": scan.angle_increment, "ranges": ranges, "range_min": scan.range_min,
            "range_max": scan.range_max, "registration_sigma": scan.registration_sigma,
            **stamp_header(scan.stamp_ns)}


def _create_or_reuse(client: ServiceClient, args: argparse.Namespace, spec: GridSpec,
                     shown: Progress) -> dict[str, Any]:
    """The map's MapInfo: created with ``spec``, or (``--append``) the existing one (said when it differs)."""
    created = create_map(client, args, None if args.growing else spec)
    if created is not None:
        return created
    if not args.append:
        raise name_taken(client, args.map)
    _, data = client.call("GET", f"/maps/{quote(args.map, safe='')}")
    info = dict(json.loads(data))
    if info.get("extent") == "growing":  # it covers wherever the scans reach
        return info
    if (info["resolution"], info["origin"], info["shape"]) != (spec.resolution, list(spec.origin), list(spec.shape)):
        shown.say(f"note: appending to {args.map!r} as it is ({info['shape'][0]} x {info['shape'][1]} cells of "
                  f"{info['resolution']} m from {info['origin']}); beams beyond it are cut at its edge")
    return info


def _through_service(args: argparse.Namespace, scans: Sequence[LaserScan], spec: GridSpec,
                     progress: FusionProgress) -> str:
    """Create (or reuse) the map, post the scans, download the files; the summary's map part."""
    client = ServiceClient(args.url, args.api_key)
    info = _create_or_reuse(client, args, spec, progress.progress)
    say_if_the_service_compiles(client, progress.progress)
    name = quote(args.map, safe="")
    version = info.get("version")
    for batch in _batches(scans, args.batch):
        body = json.dumps({"scans": [scan_json(s) for s in batch]}).encode()
        try:
            _, data = client.call("POST", f"/maps/{name}/scans", body)
        except ImportFailed as exc:  # say where the map was left, for a later --append of the rest
            raise ImportFailed(f"{exc} ({progress.scans} of {len(scans)} scans were fused into {args.map!r} "
                               "before this batch)") from None
        result = json.loads(data)
        version = result["version"]
        progress.add(int(result["scans_fused"]), int(result["rays"]))
    download_outputs(client, args, name)
    return f"{info.get('model', args.model)} map {args.map!r} version {version} on {client.url}"


# ---------------------------------------------------------------- the command


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG, description="Build a fuzzy occupancy map from a CARMEN laser log (.log or .log.gz), "
        "in-process (default) or through a running service (--url, --map).")
    p.add_argument("log", type=Path, nargs="?",
                   help="the CARMEN log (FLASER / ROBOTLASER1 lines with corrected poses); not with --trajectory")
    g = p.add_argument_group("map")
    g.add_argument("--resolution", type=positive(float), default=0.05, help="cell edge, metres (default 0.05)")
    g.add_argument("--margin", type=non_negative, default=1.0,
                   help="padding around the poses and hits, metres (default 1)")
    g.add_argument("--max-range", type=positive(float), default=None,
                   help="the scanner's maximum reading, metres; readings within 1%% of it are no-returns "
                        "(default: the log's largest reading)")
    g.add_argument("--every", type=positive(int), default=1, metavar="N", help="take every Nth scan (default 1)")
    g.add_argument("--model", choices=("fuzzy", "bayes"), default="fuzzy", help="map model (default fuzzy)")
    g.add_argument("--growing", action="store_true",
                   help="a growing map (no box: its cells are held where the scans reach; fuzzy only); the files "
                        "cover its bounds")
    g.add_argument("--batch", type=positive(int), default=32,
                   help="scans per fusion batch / request (default 32; the service takes at most "
                        "FUZZYRISK_MAX_SCANS_PER_BATCH, 256 by default)")
    add_output_options(p, nav2="write a Nav2 map_server zip (map.yaml + image) here",
                       nav2_mode="default trinary (scale needs --nav2-format png)",
                       npy="write the risk grid (float32 .npy, index [i, j] along x, y) here")
    s = add_service_options(p, append="add the scans to the map if it exists (else 409 is an error)")
    s.add_argument("--trajectory", type=Path, metavar="FILE",
                   help="instead of a LOG: put the poses of this CARMEN log (the corrected one) on --map as its "
                        "corrected trajectory, and wait for the map's rebuild")
    s.add_argument("--no-wait", action="store_true", help="with --trajectory: return once the service holds the "
                   "correction, without waiting for the rebuild")
    add_version_option(p)
    return p


#: The options of a map built from a log, which a trajectory put on an existing map does not take.
_MAP_OPTIONS = ("resolution", "margin", "max_range", "every", "model", "growing", "batch", "png", "scale", "nav2",
                "nav2_mode", "nav2_format", "npy", "append")


def _check_trajectory(p: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """A LOG, or ``--trajectory`` with ``--url`` and ``--map`` and none of a new map's options."""
    if args.trajectory is None:
        if args.log is None:
            p.error("give a LOG to import, or --trajectory FILE to correct a map's poses")
        if args.no_wait:
            p.error("--no-wait goes with --trajectory")
        return
    if args.log is not None:
        p.error("--trajectory FILE takes no LOG: the poses are FILE's")
    if not (args.url and args.map):
        p.error("--trajectory needs --url and --map: the service and the map to correct")
    given = [f"--{name.replace('_', '-')}" for name in _MAP_OPTIONS if getattr(args, name) != p.get_default(name)]
    if given:
        p.error(f"{', '.join(given)}: not with --trajectory (it corrects the poses of an existing map)")


def _put_trajectory(args: argparse.Namespace) -> str:
    """Put the log's poses on the map as its corrected trajectory, and wait for the rebuild (unless ``--no-wait``);
    the summary."""
    started = time.perf_counter()
    notes: list[str] = []  # said once the progress is up
    scans = read_carmen(args.trajectory, say=notes.append)
    stamps = [s.stamp_ns or 0 for s in scans]  # every scan of a log has one (log_stamps_ns)
    client = ServiceClient(args.url, args.api_key)
    source = args.trajectory.name
    with Progress(PROG) as shown:
        for note in notes:
            shown.say(note)
        path = sensor_path([s.pose for s in scans], stamps, map_frame(client, args.map))
        shown.say(f"{source}: {len(scans)} poses from {stamps[0] / 1e9:.3f} s to {stamps[-1] / 1e9:.3f} s, put on "
                  f"{args.map!r} as its corrected trajectory")
        status = put_trajectory(client, args.map, path)
        put = (f"{source}: {len(scans)} poses put on map {args.map!r} on {client.url}: "
               f"{status['scans_reposed']:,} scans re-posed")
        if args.no_wait:
            return (f"{put}; the map is rebuilt in the background (correction {status['id']}: GET "
                    f"/maps/{quote(args.map, safe='')}/rebuild)")
        status = wait_for_rebuild(client, args.map, status["id"], shown)
    return (f"{put}, the map rebuilt from {status['scans_total']:,} scans in {status['elapsed_s']:.1f} s: version "
            f"{status['version']}; {time.perf_counter() - started:.1f} s")


def _run(args: argparse.Namespace) -> str:
    if args.trajectory is not None:
        return _put_trajectory(args)
    if args.growing and args.model != "fuzzy":
        raise ImportFailed("--growing makes a fuzzy map: a bayes map needs a box (leave --growing out)")
    started = time.perf_counter()
    notes: list[str] = []  # said once the progress is up
    everything = read_carmen(args.log, max_range=args.max_range, say=notes.append)
    scans = everything[::args.every]
    spec = grid_for_scans(scans, args.resolution, args.margin)
    beams = BeamCounts.of(scans)
    with Progress(PROG) as shown, compile_notice(shown):
        for note in notes:
            shown.say(note)
        shown.say(f"{args.log.name}: {len(everything)} scans, map {spec.shape[0]} x {spec.shape[1]} cells of "
                  f"{spec.resolution} m from ({spec.origin[0]:g}, {spec.origin[1]:g})")
        progress = FusionProgress(len(scans), shown)
        where = (_through_service if args.url else _in_process)(args, scans, spec, progress)
    skipped = len(everything) - len(scans)
    why = f" (--every {args.every})" if skipped else ""
    return (f"{args.log.name}: {len(everything)} scans read, {progress.scans} fused, {skipped} skipped{why}; "
            f"{beams.hits + beams.no_returns:,} rays ({beams.hits:,} hits, {beams.no_returns:,} no-returns), "
            f"{beams.skipped:,} readings skipped (below {scans[0].range_min} m); {where}, "
            f"{spec.shape[0]} x {spec.shape[1]} cells of {spec.resolution} m from "
            f"({spec.origin[0]:g}, {spec.origin[1]:g}); {time.perf_counter() - started:.1f} s")


def main(argv: list[str] | None = None) -> int:
    """Run the command; the exit code (0 done, 1 failed with a message, 2 bad options)."""
    return import_main(_parser(), _run, argv, source=("log", "trajectory"), own_checks=_check_trajectory)


if __name__ == "__main__":
    sys.exit(main())

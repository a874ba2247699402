"""``python -m app.import_bag``: a map from a ROS bag (ROS 1 ``.bag``, rosbag2 with mcap or sqlite3 storage).

    python -m app.import_bag BAG [--topic T ...] [--map-frame F] [--pose-topic T [--pose-frame F]]
                             [--cloud-range-max M] [--dimensions 2|3] [--resolution 0.05] [--margin 1]
                             [--every N] [--model fuzzy|bayes] [--png FILE] [--nav2 FILE.zip] [--npy FILE]
                             [--url http://127.0.0.1:8000 --map NAME [--api-key KEY] [--append] [--body cdr|json]]

The bag is read by :class:`app.ros.bags.BagStream`, batch by batch. Without ``--origin`` (or a map to ``--append`` to) the command reads the bag
twice: once for the bounds of the placed scans (the grid), once to fuse them. Each message's sensor pose is ``T_map_frame`` at its ``header.stamp``, interpolated
along the chain of transforms from its ``header.frame_id`` to ``--map-frame``; a message the
transforms do not cover is skipped, and the summary counts why. Each message is converted by
:mod:`app.ros.messages_in`, the code the service runs on a CDR body, so the three ways in (fused here,
posted as CDR bodies, posted as JSON batches) give the same map bit for bit.

``POST /maps/{name}/bags`` (``app/service/bag_upload.py``) reads an uploaded bag with a :class:`BagStream` too.
Progress goes to stderr (``app.cli.progress``: a bar on a terminal, else a line every few seconds; a
first run says when it compiles the fusion kernels), a one-line summary to stdout; errors exit 1 with a message.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from collections import Counter
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any
from urllib.parse import quote, urlencode

from rosbags.highlevel import AnyReader

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
from app.config import Settings
from app.ops.version import add_version_option
from app.ros import messages_in
from app.ros.bags import (
    BAG_ERRORS,
    DEFAULT_CLOUD_RANGE_MAX_M,
    DEFAULT_LIMITS,
    BagOptions,
    BagScan,
    BagStream,
    BagUnreadable,
    grid_for,
)
from app.schemas import DEFAULT_FRAME_ID
from fuzzyocc import BayesMap, FuzzyMap, GridSpec

PROG = "fuzzyrisk-import-bag"


# ---------------------------------------------------------------- the command


@dataclasses.dataclass
class _Fused:
    """What the second pass did: scans fused (or posted) and their rays."""

    scans: int = 0
    rays: int = 0


#: Fuses (or posts) one batch of placed scans; returns the rays fused.
_Sink = Callable[[list[BagScan]], int]


def _in_process(args: argparse.Namespace, spec: GridSpec) -> tuple[_Sink, Callable[[], str]]:
    """Fuse each batch into a map held here; at the end, write the outputs asked for."""
    occupancy: FuzzyMap | BayesMap = FuzzyMap(spec) if args.model == "fuzzy" else BayesMap(spec)

    def fuse(batch: list[BagScan]) -> int:
        return int(occupancy.integrate_batch([s.scan for s in batch]).rays)

    def finish() -> str:
        write_outputs(args, spec, occupancy.risk(), occupancy.observed(), args.bag.name)
        return f"{args.model} map in-process"

    return fuse, finish


def _existing_map(client: ServiceClient, name: str) -> dict[str, Any] | None:
    """The service's MapInfo of ``name``, or None when it has no such map."""
    status, data = client.call("GET", f"/maps/{quote(name, safe='')}", ok=(200, 404))
    return dict(json.loads(data)) if status == 200 else None


def _spec_of(info: Mapping[str, Any]) -> GridSpec:
    return GridSpec(origin=tuple(info["origin"]), size=tuple(info["size"]), resolution=info["resolution"],
                    max_cells=2**62)  # the service's map, whatever this side's default limit


def _create(client: ServiceClient, args: argparse.Namespace, spec: GridSpec, map_frame: str) -> dict[str, Any]:
    """Create the map (in ``--map-frame``: its ``frame_id``); a name taken without ``--append`` fails."""
    created = create_map(client, args, spec, frame_id=map_frame)
    if created is None:
        raise name_taken(client, args.map)
    return created


def _through_service(args: argparse.Namespace, client: ServiceClient,
                     info: dict[str, Any]) -> tuple[_Sink, Callable[[], str]]:
    """Post each batch (one CDR body a scan, or one JSON batch); at the end, download the outputs asked for."""
    name = quote(args.map, safe="")
    version = info.get("version")
    fused = 0

    def post(target: str, body: bytes, content_type: str) -> int:
        nonlocal version, fused
        try:
            _, data = client.call("POST", target, body, content_type=content_type)
        except ImportFailed as exc:
            raise ImportFailed(f"{exc} ({fused} scans were fused into {args.map!r} before this request)") from None
        result = json.loads(data)
        version, fused = result["version"], fused + int(result["scans_fused"])
        return int(result["rays"])

    def send(batch: list[BagScan]) -> int:
        if args.body == "json":
            assert all(s.sensor is not None for s in batch)  # kept for --body json
            body = json.dumps({"scans": [s.sensor.to_json() for s in batch]}).encode()  # type: ignore[union-attr]
            return post(f"/maps/{name}/scans", body, "application/json")
        rays = 0
        for s in batch:
            query = s.pose.query()
            if s.msgtype == messages_in.POINT_CLOUD2:
                query["range_max"] = args.cloud_range_max
            assert s.cdr is not None
            rays += post(f"/maps/{name}/scans?{urlencode(query)}", s.cdr, messages_in.media_type(s.msgtype))
        return rays

    def finish() -> str:
        download_outputs(client, args, name)
        return f"{info.get('model', args.model)} map {args.map!r} version {version} on {client.url}"

    return send, finish


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG, description="Build a fuzzy occupancy map from the LaserScan and PointCloud2 topics of a ROS bag "
        "(ROS 1 .bag; rosbag2 directory, .mcap or .db3), placed by /tf and /tf_static (or a pose topic), "
        "in-process (default) or through a running service (--url, --map).")
    p.add_argument("bag", type=Path, help="the bag: a ROS 1 .bag file, a rosbag2 directory, or its .mcap / .db3 file")
    r = p.add_argument_group("what to read")
    r.add_argument("--topic", action="append", default=[], metavar="T", dest="topics",
                   help="a LaserScan or PointCloud2 topic to map (repeatable; default: all of them)")
    r.add_argument("--map-frame", default=None,
                   help="the frame the map is in: the scans are placed in it, and a map created on the service "
                        f"gets it as its frame_id (default: an --append map's own frame_id, else {DEFAULT_FRAME_ID})")
    r.add_argument("--pose-topic", metavar="T", help="place the sensor by this PoseStamped, "
                   "PoseWithCovarianceStamped or Odometry topic instead of /tf for its frame")
    r.add_argument("--pose-frame", default="base_link",
                   help="the frame a PoseStamped pose topic places (default base_link; Odometry names its own)")
    r.add_argument("--cloud-range-max", type=positive(float), default=DEFAULT_CLOUD_RANGE_MAX_M, metavar="M",
                   help="a PointCloud2's range, metres: points beyond are no-returns "
                        f"(default {DEFAULT_CLOUD_RANGE_MAX_M:g})")
    r.add_argument("--every", type=positive(int), default=1, metavar="N", help="take every Nth scan (default 1)")
    g = p.add_argument_group("map")
    g.add_argument("--dimensions", type=int, choices=(2, 3), default=None,
                   help="2 or 3 (default: 3 if a PointCloud2 topic is read, else 2)")
    g.add_argument("--resolution", type=positive(float), default=0.05, help="cell edge, metres (default 0.05)")
    g.add_argument("--margin", type=non_negative, default=1.0,
                   help="padding around the sensor positions and hits, metres (default 1)")
    g.add_argument("--origin", type=float, nargs="+", metavar="X",
                   help="the map's corner (x y [z]), metres, with --size: a fixed box instead of the data's")
    g.add_argument("--size", type=positive(float), nargs="+", metavar="W", help="the map's extent (x y [z]), metres")
    g.add_argument("--model", choices=("fuzzy", "bayes"), default="fuzzy", help="map model (default fuzzy)")
    g.add_argument("--batch", type=positive(int), default=32,
                   help="scans per fusion batch / JSON request (default 32)")
    add_output_options(p, png="write the risk picture (PNG; a 3-D map's max-risk projection) here")
    s = add_service_options(p, append="add the scans to the map if it exists")
    s.add_argument("--body", choices=("cdr", "json"), default="cdr",
                   help="post each message as its CDR body with its pose (default), or JSON batches of --batch scans")
    add_version_option(p)
    return p


def _check_box(p: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """``--origin`` and ``--size`` (and ``--dimensions``) agree."""
    if (args.origin is None) != (args.size is None) or (args.origin and len(args.origin) != len(args.size)):
        p.error("--origin and --size go together, with as many values each (2 for a 2-D map, 3 for a 3-D map)")
    if args.origin and args.dimensions and len(args.origin) != args.dimensions:
        p.error(f"--origin and --size need {args.dimensions} values for --dimensions {args.dimensions}")


def _dimensions(args: argparse.Namespace) -> int:
    if args.dimensions is not None:
        return int(args.dimensions)
    if args.origin is not None:
        return len(args.origin)
    try:
        with AnyReader([args.bag]) as reader:
            chosen = [c for c in reader.connections if c.msgtype in messages_in.MSGTYPES
                      and (not args.topics or c.topic in args.topics)]
    except BAG_ERRORS as exc:
        raise BagUnreadable(f"{args.bag.name}: not a readable bag ({exc})") from None
    return 3 if any(c.msgtype == messages_in.POINT_CLOUD2 for c in chosen) else 2


def summary_reasons(skipped: Counter[str]) -> str:
    """``3 before the first transform odom -> base_link, 1 no usable beam``, most frequent first."""
    return ", ".join(f"{n} {why}" for why, n in skipped.most_common()) or "none"


def _run(args: argparse.Namespace) -> str:
    """Read the bag in two passes (the first only to size the map: without ``--origin`` or an existing map),
    fusing or posting each batch as it is read: the bag is never held in memory."""
    with Progress(PROG) as progress, compile_notice(progress):
        return _import(args, progress, time.perf_counter())


def _import(args: argparse.Namespace, progress: Progress, started: float) -> str:
    dims = _dimensions(args)
    client = ServiceClient(args.url, args.api_key) if args.url else None
    existing = _existing_map(client, args.map) if client is not None and args.append else None
    if existing is not None and existing["dimensions"] != dims:
        raise ImportFailed(f"map {args.map!r} on {args.url} is {existing['dimensions']}-D; pass --dimensions "
                           f"{existing['dimensions']} to append to it")
    # the frame the scans are placed in: as given, else the existing map's own, else the default
    map_frame = args.map_frame or (existing or {}).get("frame_id") or DEFAULT_FRAME_ID
    options = BagOptions(map_frame=map_frame, topics=tuple(args.topics), pose_topic=args.pose_topic,
                         pose_frame=args.pose_frame, cloud_range_max=args.cloud_range_max, every=args.every)
    max_cells = Settings.model_fields["max_map_cells"].default
    placed = ""
    if existing is not None:
        spec = _spec_of(existing)
    elif args.origin is not None:
        spec = GridSpec(origin=tuple(args.origin), size=tuple(args.size), resolution=args.resolution,
                        max_cells=max_cells)
    else:  # a first pass: the bounds of every placed scan, nothing kept
        with BagStream(args.bag, options, dims=dims, limits=DEFAULT_LIMITS,
                       progress=lambda done, _: progress.update(done)) as sizing:
            progress.stage("reading to size the map", sizing.total, "messages")
            spec = grid_for((s.scan for s in sizing), dims, args.resolution, args.margin, max_cells)
            progress.close()
            placed = f"; {sizing.placed} placed"
    if client is None:
        send, finish = _in_process(args, spec)
    else:
        say_if_the_service_compiles(client, progress)
        send, finish = _through_service(args, client, existing or _create(client, args, spec, map_frame))
    shape = " x ".join(str(n) for n in spec.shape)
    fused = _Fused()
    with BagStream(args.bag, options, dims=dims, limits=DEFAULT_LIMITS, keep_cdr=client is not None and
                   args.body == "cdr", keep_sensor=client is not None and args.body == "json",
                   progress=lambda done, _: progress.update(done, f"{fused.scans} scans fused")) as bag:
        progress.say(f"{args.bag.name}: {bag.total} scan messages on {', '.join(sorted(bag.topics))}, "
                     f"{bag.transforms} transforms{placed}; map {shape} cells of {spec.resolution} m from "
                     f"({', '.join(f'{v:g}' for v in spec.origin)}) in frame {map_frame}")
        progress.stage("fusing", bag.total, "messages")
        for batch in bag.batches(args.batch):
            fused.rays += send(batch)
            fused.scans += len(batch)
        progress.update(bag.messages, f"{fused.scans} scans fused")
        progress.close()
        where = finish()
        elapsed = time.perf_counter() - started
        return (f"{args.bag.name}: {bag.messages} scan messages read, {fused.scans} fused, "
                f"{sum(bag.skipped.values())} skipped ({summary_reasons(bag.skipped)}); {fused.rays:,} rays; "
                f"{where}, {shape} cells of {spec.resolution} m; {elapsed:.1f} s "
                f"({fused.scans / max(elapsed, 1e-9):.0f} scans/s)")


def main(argv: list[str] | None = None) -> int:
    """Run the command; the exit code (0 done, 1 failed with a message, 2 bad options)."""
    return import_main(_parser(), _run, argv, source="bag", own_checks=_check_box)


if __name__ == "__main__":
    sys.exit(main())

"""``python -m app.import_log``: a map from a recorded CARMEN laser log, in-process or through the service.

    python -m app.import_log LOG [--resolution 0.05] [--margin 1] [--every N] [--max-range M]
                             [--model fuzzy|bayes] [--png FILE] [--nav2 FILE.zip] [--npy FILE]
                             [--url http://127.0.0.1:8000 --map NAME [--api-key KEY] [--append]]

The map's bounds are those of the log's poses and hits, padded by ``--margin`` (see
:func:`fuzzyocc.carmen.grid_for_scans`). Without ``--url`` the scans are fused here, into
``FuzzyMap(spec)`` (or ``BayesMap``), and the files are rendered by :mod:`app.formats.exports`, as the
service renders them. With ``--url`` the map is created on the service (with the same sensor
model) and the scans are posted in order as JSON batches; the files are then downloaded.
Either way the scans are fused in log order, so a new map's risk is the same bit for bit.
Progress goes to stderr, a one-line summary to stdout; errors exit 1 with a message.
"""

from __future__ import annotations

import argparse
import dataclasses
import http.client
import json
import math
import os
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TextIO
from urllib.parse import quote, urlencode, urlsplit

import numpy as np

from app.formats import exports
from fuzzyocc import BayesMap, FuzzyMap, GridSpec, LaserScan, SensorModel
from fuzzyocc.carmen import grid_for_scans, read_carmen

PROG = "fuzzyrisk-import-log"
#: How long a batch may keep meeting 503 (a full line of batches, a full disk) before we give up, seconds.
RETRY_FOR_S = 120.0
#: Per-request socket timeout, seconds (a 256-scan batch of a big map fuses in well under this).
REQUEST_TIMEOUT_S = 300.0


class ImportFailed(Exception):
    """A failure to report in one line (the service's answer, a bad option); exit code 1."""


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


class Progress:
    """``scans fused, rays, elapsed`` on a stream, at most once a second and once at the end."""

    def __init__(self, total: int, started: float, stream: TextIO, every_s: float = 1.0) -> None:
        self.total, self.started, self.stream, self.every_s = total, started, stream, every_s
        self.scans = self.rays = 0
        self._last = -math.inf

    def add(self, scans: int, rays: int) -> None:
        self.scans += scans
        self.rays += rays
        now = time.perf_counter()
        if now - self._last >= self.every_s or self.scans == self.total:
            self._last = now
            print(f"{PROG}: {self.scans}/{self.total} scans fused, {self.rays:,} rays, "
                  f"{now - self.started:.1f} s", file=self.stream, flush=True)


def _batches(scans: Sequence[LaserScan], size: int) -> list[Sequence[LaserScan]]:
    return [scans[i:i + size] for i in range(0, len(scans), size)]


# ---------------------------------------------------------------- in-process


def _in_process(args: argparse.Namespace, scans: Sequence[LaserScan], spec: GridSpec, progress: Progress) -> str:
    """Fuse here and write the files; the summary's map part."""
    occupancy: FuzzyMap | BayesMap = FuzzyMap(spec) if args.model == "fuzzy" else BayesMap(spec)
    for batch in _batches(scans, args.batch):
        stats = occupancy.integrate_batch(batch)
        progress.add(stats.scans, stats.rays)
    risk, observed = occupancy.risk(), occupancy.observed()
    if args.png:
        text = {"source": args.log.name, "resolution": repr(spec.resolution), "origin": repr(list(spec.origin))}
        args.png.write_bytes(exports.risk_png(risk, observed, scale=args.scale, text=text))
    if args.nav2:
        args.nav2.write_bytes(exports.nav2_zip(risk, observed, resolution=spec.resolution,
                                           origin_xy=(spec.origin[0], spec.origin[1]), mode=args.nav2_mode,
                                           image_format=args.nav2_format))
    if args.npy:
        args.npy.write_bytes(exports.npy_bytes(np.asarray(risk, dtype=np.float32)))
    return f"{args.model} map in-process"


# ---------------------------------------------------------------- through the service


def _detail(body: bytes) -> str:
    """The service's error body (``{code, message, details}``) as one line (the body itself if it is not that)."""
    try:
        error = json.loads(body)
        code, message = error["code"], error["message"]
    except (ValueError, KeyError, TypeError):
        return body.decode("utf-8", "replace").strip()[:500] or "(empty body)"
    return f"{code}: {message}"


class ServiceClient:
    """The few calls the import makes, over the standard library's ``http.client``.

    One connection per request: a kept-alive connection the server has closed meanwhile would
    leave a POST's fate unknown, and a resent batch would be fused twice.
    """

    def __init__(self, url: str, api_key: str | None, retry_for_s: float = RETRY_FOR_S) -> None:
        parts = urlsplit(url)
        if parts.scheme not in ("http", "https") or not parts.hostname:
            raise ImportFailed(f"--url must look like http://127.0.0.1:8000, got {url!r}")
        self.url = url.rstrip("/")
        self._https = parts.scheme == "https"
        self._host, self._port = parts.hostname, parts.port
        self._prefix = parts.path.rstrip("/")  # a service behind a reverse proxy's root path
        self._headers = {"Authorization": f"Bearer {api_key}"} if api_key else {}
        self.retry_for_s = retry_for_s

    def _once(self, method: str, path: str, body: bytes | None, content_type: str) -> tuple[int, dict[str, str], bytes]:
        cls = http.client.HTTPSConnection if self._https else http.client.HTTPConnection
        conn = cls(self._host, self._port, timeout=REQUEST_TIMEOUT_S)
        headers = {**self._headers, **({"Content-Type": content_type} if body is not None else {})}
        try:
            conn.request(method, self._prefix + path, body=body, headers=headers)
            response = conn.getresponse()
            return response.status, {k.lower(): v for k, v in response.getheaders()}, response.read()
        except (OSError, http.client.HTTPException) as exc:
            raise ImportFailed(f"cannot reach the service at {self.url} ({method} {path}): {exc}") from None
        finally:
            conn.close()

    def call(self, method: str, path: str, body: bytes | None = None, *, ok: tuple[int, ...] = (200,),
             content_type: str = "application/json") -> tuple[int, bytes]:
        """The status and body of an answer in ``ok``; 503 is retried after its Retry-After, any other status raises."""
        deadline = time.monotonic() + self.retry_for_s
        while True:
            status, headers, data = self._once(method, path, body, content_type)
            if status in ok:
                return status, data
            if status == 503 and time.monotonic() < deadline:
                try:
                    wait = float(headers.get("retry-after", "1"))
                except ValueError:  # the HTTP-date form: the service never sends it
                    wait = 1.0
                time.sleep(min(max(wait, 0.05), max(0.0, deadline - time.monotonic())))
                continue
            raise ImportFailed(f"{method} {self.url}{path} answered {status}: {_detail(data)}")


def _scan_json(scan: LaserScan) -> dict[str, Any]:
    x, y, theta = scan.pose
    # json writes the shortest repr that reads back to the same float64: the service fuses our numbers
    ranges = ["inf" if math.isinf(r) else r for r in scan.ranges.tolist()]
    return {"pose": {"x": x, "y": y, "theta": theta}, "angle_min": scan.angle_min,
            "angle_increment": scan.angle_increment, "ranges": ranges, "range_min": scan.range_min,
            "range_max": scan.range_max, "registration_sigma": scan.registration_sigma}


def _create_or_reuse(client: ServiceClient, args: argparse.Namespace, spec: GridSpec) -> dict[str, Any]:
    """The map's MapInfo: created with ``spec``, or (``--append``) the existing one."""
    request = {"name": args.map, "dimensions": 2, "resolution": spec.resolution, "origin": list(spec.origin),
               "size": list(spec.size), "model": args.model,
               # the in-process default, stated: both paths must fuse with the same sensor model
               "sensor": dataclasses.asdict(SensorModel())}
    status, data = client.call("POST", "/maps", json.dumps(request).encode(), ok=(201, 409))
    if status == 201:
        return dict(json.loads(data))
    if not args.append:
        raise ImportFailed(f"a map named {args.map!r} exists on {client.url}: pass --append to add the scans to it, "
                           "or choose another --map")
    _, data = client.call("GET", f"/maps/{quote(args.map, safe='')}")
    info = dict(json.loads(data))
    if (info["resolution"], info["origin"], info["shape"]) != (spec.resolution, list(spec.origin), list(spec.shape)):
        print(f"{PROG}: note: appending to {args.map!r} as it is ({info['shape'][0]} x {info['shape'][1]} cells of "
              f"{info['resolution']} m from {info['origin']}); beams beyond it are cut at its edge",
              file=sys.stderr)
    return info


def _through_service(args: argparse.Namespace, scans: Sequence[LaserScan], spec: GridSpec, progress: Progress) -> str:
    """Create (or reuse) the map, post the scans, download the files; the summary's map part."""
    client = ServiceClient(args.url, args.api_key)
    info = _create_or_reuse(client, args, spec)
    name = quote(args.map, safe="")
    version = info.get("version")
    for batch in _batches(scans, args.batch):
        body = json.dumps({"scans": [_scan_json(s) for s in batch]}).encode()
        try:
            _, data = client.call("POST", f"/maps/{name}/scans", body)
        except ImportFailed as exc:  # say where the map was left, for a later --append of the rest
            raise ImportFailed(f"{exc} ({progress.scans} of {len(scans)} scans were fused into {args.map!r} "
                               "before this batch)") from None
        result = json.loads(data)
        version = result["version"]
        progress.add(int(result["scans_fused"]), int(result["rays"]))
    downloads = [
        (args.png, f"/maps/{name}/risk?" + urlencode({"format": "png", "scale": args.scale})),
        (args.nav2, f"/maps/{name}/export/nav2?" + urlencode({"mode": args.nav2_mode, "format": args.nav2_format})),
        (args.npy, f"/maps/{name}/risk?format=npy"),
    ]
    for path, target in downloads:
        if path:
            path.write_bytes(client.call("GET", target)[1])
    return f"{info.get('model', args.model)} map {args.map!r} version {version} on {client.url}"


# ---------------------------------------------------------------- the command


def _positive(kind: type[int] | type[float]) -> Any:
    def parse(text: str) -> int | float:
        value = kind(text)
        if not (math.isfinite(value) and value > 0):
            raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
        return value
    parse.__name__ = kind.__name__
    return parse


def _non_negative(text: str) -> float:
    value = float(text)
    if not (math.isfinite(value) and value >= 0.0):
        raise argparse.ArgumentTypeError(f"must be a number >= 0, got {text}")
    return value


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG, description="Build a fuzzy occupancy map from a CARMEN laser log (.log or .log.gz), "
        "in-process (default) or through a running service (--url, --map).")
    p.add_argument("log", type=Path, help="the CARMEN log (FLASER / ROBOTLASER1 lines with corrected poses)")
    g = p.add_argument_group("map")
    g.add_argument("--resolution", type=_positive(float), default=0.05, help="cell edge, metres (default 0.05)")
    g.add_argument("--margin", type=_non_negative, default=1.0,
                   help="padding around the poses and hits, metres (default 1)")
    g.add_argument("--max-range", type=_positive(float), default=None,
                   help="the scanner's maximum reading, metres; readings within 1%% of it are no-returns "
                        "(default: the log's largest reading)")
    g.add_argument("--every", type=_positive(int), default=1, metavar="N", help="take every Nth scan (default 1)")
    g.add_argument("--model", choices=("fuzzy", "bayes"), default="fuzzy", help="map model (default fuzzy)")
    g.add_argument("--batch", type=_positive(int), default=32,
                   help="scans per fusion batch / request (default 32; the service takes at most "
                        "FUZZYRISK_MAX_SCANS_PER_BATCH, 256 by default)")
    o = p.add_argument_group("output")
    o.add_argument("--png", type=Path, help="write the risk picture (PNG) here")
    o.add_argument("--scale", type=_positive(int), default=1, help="PNG pixels per cell (default 1)")
    o.add_argument("--nav2", type=Path, metavar="FILE.zip", help="write a Nav2 map_server zip (map.yaml + image) here")
    o.add_argument("--nav2-mode", choices=("trinary", "scale", "raw"), default="trinary",
                   help="default trinary (scale needs --nav2-format png)")
    o.add_argument("--nav2-format", choices=("pgm", "png"), default="pgm", help="default pgm")
    o.add_argument("--npy", type=Path, help="write the risk grid (float32 .npy, index [i, j] along x, y) here")
    s = p.add_argument_group("through the service")
    s.add_argument("--url", help="the service, e.g. http://127.0.0.1:8000 (default: fuse in-process)")
    s.add_argument("--map", help="name of the map to create on the service")
    s.add_argument("--api-key", default=os.environ.get("FUZZYRISK_API_KEY") or None,
                   help="the service's API key (default: $FUZZYRISK_API_KEY)")
    s.add_argument("--append", action="store_true", help="add the scans to the map if it exists (else 409 is an error)")
    return p


def _check_options(p: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    if args.url and not args.map:
        p.error("--url needs --map NAME")
    if not args.url and (args.map or args.append):
        p.error("--map and --append need --url (without it the map is built in-process)")
    if args.nav2 is not None:
        try:
            exports.check_nav2_format(args.nav2_mode, args.nav2_format)
        except ValueError as exc:
            p.error(f"--nav2-mode {args.nav2_mode} --nav2-format {args.nav2_format}: {exc}")
    for option in ("png", "nav2", "npy"):
        path = getattr(args, option)
        if path is not None and not path.parent.is_dir():  # before minutes of fusion, not after
            p.error(f"--{option}: directory {str(path.parent)!r} does not exist")


def _run(args: argparse.Namespace) -> str:
    started = time.perf_counter()
    everything = read_carmen(args.log, max_range=args.max_range)
    scans = everything[::args.every]
    spec = grid_for_scans(scans, args.resolution, args.margin)
    beams = BeamCounts.of(scans)
    print(f"{PROG}: {args.log.name}: {len(everything)} scans, map {spec.shape[0]} x {spec.shape[1]} cells of "
          f"{spec.resolution} m from ({spec.origin[0]:g}, {spec.origin[1]:g})", file=sys.stderr, flush=True)
    progress = Progress(len(scans), started, sys.stderr)
    where = (_through_service if args.url else _in_process)(args, scans, spec, progress)
    skipped = len(everything) - len(scans)
    why = f" (--every {args.every})" if skipped else ""
    return (f"{args.log.name}: {len(everything)} scans read, {progress.scans} fused, {skipped} skipped{why}; "
            f"{beams.hits + beams.no_returns:,} rays ({beams.hits:,} hits, {beams.no_returns:,} no-returns), "
            f"{beams.skipped:,} readings skipped (below {scans[0].range_min} m); {where}, "
            f"{spec.shape[0]} x {spec.shape[1]} cells of {spec.resolution} m from "
            f"({spec.origin[0]:g}, {spec.origin[1]:g}); {time.perf_counter() - started:.1f} s")


def run_command(prog: str, run: Callable[[], str], source: Path) -> int:
    """Run an import command: its summary on stdout, or one line on stderr; the exit code (0 done, 1 failed,
    130 interrupted). Shared by the log and the bag importers."""
    try:
        summary = run()
    except FileNotFoundError as exc:
        print(f"{prog}: error: {exc.filename or source}: no such file", file=sys.stderr)
        return 1
    except (ImportFailed, ValueError, OSError) as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
    print(summary, flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    """Run the command; the exit code (0 done, 1 failed with a message, 2 bad options)."""
    parser = _parser()
    args = parser.parse_args(argv)
    _check_options(parser, args)
    return run_command(PROG, lambda: _run(args), args.log)


if __name__ == "__main__":
    sys.exit(main())

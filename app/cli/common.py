"""What the two importers (``app.cli.import_log``, ``app.cli.import_bag``) share: their command's frame.

The option types and the checks of the options both take (the service, the output files), the
client of the service's HTTP API, the line said when kernels compile (here, or in the service),
the files written in-process or downloaded from the service, and ``import_main``: parse, check,
run, one line of summary or error. Their progress is ``app.cli.progress``.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import http.client
import json
import math
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any
from urllib.parse import urlencode, urlsplit

import numpy as np

from app.cli.progress import Progress
from app.formats import exports
from app.ops.compile_notice import on_first_compile
from fuzzyocc import GridSpec, SensorModel

#: How long a batch may keep meeting 503 (a full line of batches, a full disk) before we give up, seconds.
RETRY_FOR_S = 120.0
#: Per-request socket timeout, seconds (a 256-scan batch of a big map fuses in well under this).
REQUEST_TIMEOUT_S = 300.0


class ImportFailed(Exception):
    """A failure to report in one line (the service's answer, a bad option); exit code 1."""


# ---------------------------------------------------------------- options


def positive(kind: type[int | float]) -> Any:
    """An argparse type: a finite number of ``kind`` above 0."""
    def parse(text: str) -> int | float:
        value = kind(text)
        if not (math.isfinite(value) and value > 0):
            raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
        return value
    parse.__name__ = kind.__name__
    return parse


def non_negative(text: str) -> float:
    """An argparse type: a finite float of at least 0."""
    value = float(text)
    if not (math.isfinite(value) and value >= 0.0):
        raise argparse.ArgumentTypeError(f"must be a number >= 0, got {text}")
    return value


def add_output_options(p: argparse.ArgumentParser, *, png: str = "write the risk picture (PNG) here",
                       nav2: str = "write a Nav2 map_server zip here", nav2_mode: str = "default trinary",
                       npy: str = "write the risk grid (float32 .npy) here") -> None:
    """The ``output`` group: the files to write; the keywords are the help an importer gives of them."""
    o = p.add_argument_group("output")
    o.add_argument("--png", type=Path, help=png)
    o.add_argument("--scale", type=positive(int), default=1, help="PNG pixels per cell (default 1)")
    o.add_argument("--nav2", type=Path, metavar="FILE.zip", help=nav2)
    o.add_argument("--nav2-mode", choices=("trinary", "scale", "raw"), default="trinary", help=nav2_mode)
    o.add_argument("--nav2-format", choices=("pgm", "png"), default="pgm", help="default pgm")
    o.add_argument("--npy", type=Path, help=npy)


def add_service_options(p: argparse.ArgumentParser, *, append: str) -> argparse._ArgumentGroup:
    """The ``through the service`` group (``append``: the help of ``--append``); returned for an importer's own."""
    s = p.add_argument_group("through the service")
    s.add_argument("--url", help="the service, e.g. http://127.0.0.1:8000 (default: fuse in-process)")
    s.add_argument("--map", help="name of the map to create on the service")
    s.add_argument("--api-key", default=os.environ.get("FUZZYRISK_API_KEY") or None,
                   help="the service's API key (default: $FUZZYRISK_API_KEY)")
    s.add_argument("--append", action="store_true", help=append)
    return s


def check_options(p: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """The checks of the service and output options, before any reading: a mistake exits 2 with its usage."""
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


# ---------------------------------------------------------------- compiling and outputs


#: Said once, at the first compilation of a kernel (a cold numba cache), by an import fused here.
COMPILING = "compiling the fusion kernels (first run only: numba caches them for later runs)..."


def compile_notice(progress: Progress) -> contextlib.AbstractContextManager[None]:
    """Within the block, say ``COMPILING`` when numba starts to compile a kernel (never when all are cached)."""
    return on_first_compile(lambda: progress.say(COMPILING))


def write_outputs(args: argparse.Namespace, spec: GridSpec, risk: np.ndarray, observed: np.ndarray,
                  source: str) -> None:
    """Write the files asked for of a map fused here, as the service renders them (a 3-D map's PNG and Nav2
    map: its max-risk projection along z); ``source``: the input's name, in the PNG's text."""
    if args.png or args.nav2:
        flat, seen = (risk, observed) if spec.ndim == 2 else exports.project_z(
            risk, observed, origin_z=spec.origin[2], resolution=spec.resolution)
        if args.png:
            text = {"source": source, "resolution": repr(spec.resolution), "origin": repr(list(spec.origin))}
            args.png.write_bytes(exports.risk_png(flat, seen, scale=args.scale, text=text))
        if args.nav2:
            args.nav2.write_bytes(exports.nav2_zip(flat, seen, resolution=spec.resolution,
                                                   origin_xy=(spec.origin[0], spec.origin[1]),
                                                   mode=args.nav2_mode, image_format=args.nav2_format))
    if args.npy:
        args.npy.write_bytes(exports.npy_bytes(np.asarray(risk, dtype=np.float32)))


# ---------------------------------------------------------------- the service


def _detail(body: bytes) -> str:
    """The service's error body (``{code, message, details}``) as one line (the body itself if it is not that)."""
    try:
        error = json.loads(body)
        code, message = error["code"], error["message"]
    except (ValueError, KeyError, TypeError):
        return body.decode("utf-8", "replace").strip()[:500] or "(empty body)"
    return f"{code}: {message}"


class ServiceClient:
    """The few calls an import makes, over the standard library's ``http.client``.

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


def say_if_the_service_compiles(client: ServiceClient, progress: Progress) -> None:
    """Say so when the service is still compiling its fusion kernels (its first start): the first batch waits for
    them. Its ``GET /ready`` tells; a service that does not answer it is not waited for here."""
    try:
        status, data = client.call("GET", "/ready", ok=(200, 503))
        compiling = status == 503 and json.loads(data).get("kernels_compiled") is False
    except (ImportFailed, ValueError, AttributeError):
        return
    if compiling:
        progress.say(f"the service at {client.url} is still compiling its fusion kernels (its first start); "
                     "the first batch waits for them...")


def create_map(client: ServiceClient, args: argparse.Namespace, spec: GridSpec | None, **extra: Any
               ) -> dict[str, Any] | None:
    """``POST /maps`` of ``--map`` with ``spec`` (None: a growing 2-D map at ``--resolution``), ``--model`` and
    ``extra`` fields: its MapInfo; None when the name is taken (409)."""
    box: dict[str, Any] = ({"dimensions": 2, "resolution": args.resolution, "extent": "growing"} if spec is None else
                           {"dimensions": spec.ndim, "resolution": spec.resolution, "origin": list(spec.origin),
                            "size": list(spec.size)})
    request = {"name": args.map, **box, "model": args.model,
               # the in-process default, stated: both paths must fuse with the same sensor model
               "sensor": dataclasses.asdict(SensorModel()), **extra}
    status, data = client.call("POST", "/maps", json.dumps(request).encode(), ok=(201, 409))
    return dict(json.loads(data)) if status == 201 else None


def name_taken(client: ServiceClient, name: str) -> ImportFailed:
    """The error of a ``--map`` name the service already has, without ``--append``."""
    return ImportFailed(f"a map named {name!r} exists on {client.url}: pass --append to add the scans to it, "
                        "or choose another --map")


def download_outputs(client: ServiceClient, args: argparse.Namespace, name: str) -> None:
    """Download the files asked for of the service's map ``name`` (quoted for a path)."""
    downloads = [
        (args.png, f"/maps/{name}/risk?" + urlencode({"format": "png", "scale": args.scale})),
        (args.nav2, f"/maps/{name}/export/nav2?" + urlencode({"mode": args.nav2_mode, "format": args.nav2_format})),
        (args.npy, f"/maps/{name}/risk?format=npy"),
    ]
    for path, target in downloads:
        if path:
            path.write_bytes(client.call("GET", target)[1])


# ---------------------------------------------------------------- the command


def run_command(prog: str, run: Callable[[], str], source: Path) -> int:
    """Run an import: its summary on stdout, or one line on stderr; the exit code (0 done, 1 failed,
    130 interrupted). ``source``: the input, named when a missing file has no name of its own."""
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


def import_main(parser: argparse.ArgumentParser, run: Callable[[argparse.Namespace], str], argv: list[str] | None,
                *, source: str | tuple[str, ...],
                own_checks: Callable[[argparse.ArgumentParser, argparse.Namespace], None] | None = None) -> int:
    """An importer's ``main``: parse ``argv``, check the importer's own options then the shared ones
    (``check_options``), run; the exit code (0 done, 1 failed with a message, 2 bad options, 130 interrupted).
    ``source``: the name of the input's argument (or of each, the one given being the input)."""
    args = parser.parse_args(argv)
    if own_checks is not None:
        own_checks(parser, args)
    check_options(parser, args)
    given = [getattr(args, name) for name in ((source,) if isinstance(source, str) else source)]
    return run_command(parser.prog, lambda: run(args), next(path for path in given if path is not None))

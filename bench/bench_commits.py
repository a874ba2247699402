"""Small commits beside big ones: an innocent map's batch commit latency while another map commits 8 MB batches.

``python -m bench.bench_commits [--seconds 15]``. The service's own ``SqliteStorage`` and
``GroupCommitter`` on the data disk (a temporary directory under ``--dir``), three windows:

* ``alone``: small batches (2 KB) only, one every 50 ms;
* ``in rows``: the same beside an 8 MB batch every 0.5 s of another map, its payload in its row
  (``INLINE_BYTES`` raised for the window: how the store wrote every batch before payload files);
* ``as files``: the same, with payloads over ``INLINE_BYTES`` written to files before their commit
  (what the service does).

Prints each window's p50 / p90 / p99 / max and the p99 as a multiple of ``alone``'s.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import app.storage.committer
import app.storage.sqlite
from app.storage.committer import GroupCommitter
from app.ops.metrics import Metrics
from app.storage import BatchRecord, SqliteStorage

SMALL, BIG, BIG_EVERY_S, SMALL_EVERY_S = 2_000, 8_000_000, 0.5, 0.05


@contextmanager
def _inline_limit(limit: int) -> Iterator[None]:
    # set in the modules that read it: the SQLite store (a payload to a file or its row) and the committer
    saved = app.storage.sqlite.INLINE_BYTES
    app.storage.sqlite.INLINE_BYTES = app.storage.committer.INLINE_BYTES = limit
    try:
        yield
    finally:
        app.storage.sqlite.INLINE_BYTES = app.storage.committer.INLINE_BYTES = saved


def _window(directory: Path, seconds: float, big: bool) -> list[float]:
    """Commit latencies (s) of the small batches of one window."""
    storage = SqliteStorage(directory / "fuzzyrisk.sqlite3")
    committer = GroupCommitter(storage, Metrics())
    for name in ("innocent", "heavy"):
        storage.create_map(name, {"name": name}, "t")
    until = time.monotonic() + seconds
    payload = os.urandom(BIG)

    def heavy() -> None:
        while time.monotonic() < until:
            time.sleep(BIG_EVERY_S)
            committer.append(BatchRecord("heavy", None, payload, "t", 1)).result()

    thread = threading.Thread(target=heavy)
    if big:
        thread.start()
    latencies = []
    try:
        while time.monotonic() < until:
            t0 = time.perf_counter()
            committer.append(BatchRecord("innocent", None, os.urandom(SMALL), "t", 1)).result()
            latencies.append(time.perf_counter() - t0)
            time.sleep(SMALL_EVERY_S)
    finally:
        if big:
            thread.join()
        committer.shutdown()
        storage.close()
    return latencies


def _summary(latencies: list[float]) -> tuple[float, str]:
    ordered = sorted(latencies)

    def at(q: float) -> float:
        return ordered[min(len(ordered) - 1, int(q * len(ordered)))] * 1e3

    return at(0.99), (f"n={len(ordered)} p50 {at(0.5):.1f} p90 {at(0.9):.1f} p99 {at(0.99):.1f} "
                      f"max {ordered[-1] * 1e3:.1f} ms")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=15.0, help="length of each window")
    ap.add_argument("--dir", type=Path, default=Path.cwd(), help="where the temporary databases go (the data disk)")
    args = ap.parse_args(argv)
    windows = [("alone", False, app.storage.INLINE_BYTES), ("in rows", True, 2 * BIG),
               ("as files", True, app.storage.INLINE_BYTES)]
    results = {}
    for label, big, limit in windows:
        with tempfile.TemporaryDirectory(dir=args.dir) as tmp, _inline_limit(limit):
            results[label] = _summary(_window(Path(tmp), args.seconds, big))
    quiet = results["alone"][0]
    print(f"# small ({SMALL} B) commits every {SMALL_EVERY_S * 1e3:.0f} ms; beside them, {BIG / 1e6:.0f} MB batches "
          f"of another map every {BIG_EVERY_S} s ({args.seconds:g} s windows, {args.dir})")
    for label, (p99, text) in results.items():
        print(f"{label:9} {text}  (p99 {p99 / quiet:.1f}x alone)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

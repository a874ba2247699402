"""Map grids shared with the planner workers by (map, version), and the fields the workers keep.

A plan needs the map's risk and observed mask at one version, and the worker turns them into a
``planning.RiskField`` whose dilation by the robot (tens of milliseconds on a map of millions of
cells) it computes per radius and caches on that field. Shipping the arrays with every plan (a
pickle through a pipe) and rebuilding the field every time cost more than the search itself on
a big map, so instead:

* the server (``PlanGrids``) writes a map version's risk and observed mask once, as two ``.npy``
  files in ``<data dir>/plan-grids/<run>/``, when the first plan on that version asks for it, and
  hands the workers a ``GridRef`` (the files' paths, resolution and origin, a few hundred bytes);
* each worker (``FieldCache``) keeps the ``RiskField`` of the refs it has planned on, least
  recently used first out, so a field's dilations are reused by every later plan on that version.

Bounds and cleanup: the files of all versions together stay within ``max_bytes``
(``FUZZYRISK_PLAN_CACHE_BYTES``): the least recently used grid no plan is using goes first, and a
grid that cannot fit is shipped to the worker with its plan as before. A version's files go
once a newer version is applied or the map is deleted (at once, or when the last plan using them
ends), and the run's directory goes at shutdown; a directory left by a killed service is removed at
the next start (each run holds a lock on its own). A data directory that refuses the files (full,
read-only) costs nothing but the shipping. Each worker keeps at most ``max_bytes`` of fields too
(risk, observed mask and the dilations it computed), and drops the field of a ref whose files are
gone (a newer version, a deleted map), which no plan can ask for again.

A ref names one (map, version): a map's arrays at a version never change, and ``MapEntry.uid``
tells a deleted map from a new one of the same name, so a cached field is always the right one.
"""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import itertools
import logging
import os
import shutil
from collections import OrderedDict
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np

LOG = logging.getLogger("fuzzyrisk.plans")

#: Name of the directory under the data directory that holds the runs' grids.
DIRECTORY = "plan-grids"
#: A run's lock file: held (flock) for as long as the run's service lives.
LOCK_NAME = "lock"
#: Room kept for each ``.npy`` header when a grid's bytes are reserved before it is written.
_HEADER_ROOM = 4096

Runner = Callable[..., Awaitable[Any]]


@dataclass(frozen=True)
class GridRef:
    """What a worker needs to plan on a published grid: its files, resolution, origin and shape (cells along each
    axis: a growing map's grid is a window, which a later plan reuses only if it needs that very window)."""

    risk_path: str
    observed_path: str
    resolution: float
    origin: tuple[float, ...]
    shape: tuple[int, ...] = ()


# ---------------------------------------------------------------- the server's side


@dataclass(eq=False)
class _Grid:
    key: tuple[int, int]  # (map uid, version)
    ref: GridRef
    nbytes: int  # on disk
    users: int = 0
    retired: bool = False  # a newer version exists, or the map is gone: deleted once unused
    deleted: bool = False


@dataclass(eq=False)
class Lease:
    """A plan's hold on a published grid: its files stay until ``release``."""

    grids: PlanGrids
    grid: _Grid
    released: bool = field(default=False)

    @property
    def ref(self) -> GridRef:
        return self.grid.ref

    @property
    def version(self) -> int:
        return self.grid.key[1]

    def release(self) -> None:
        if not self.released:
            self.released = True
            self.grids._release(self.grid)


class PlanGrids:
    """Map versions published as files for the planner workers, within ``max_bytes`` on disk.

    Runs on the event loop (no locks: every method but the file writes runs there); the writes run
    through ``run`` (a thread). ``max_bytes`` 0 publishes nothing: every plan ships its grid.
    """

    def __init__(self, root: Path, max_bytes: int, run: Runner, on_bytes: Callable[[int], None] | None = None) -> None:
        self.root = root
        self.max_bytes = max_bytes
        self._run = run
        self._on_bytes = on_bytes
        self._dir: Path | None = None
        self._lock: IO[bytes] | None = None
        self._grids: OrderedDict[tuple[int, int], _Grid] = OrderedDict()  # least recently used first
        self._pending: dict[tuple[int, int], asyncio.Future[None]] = {}
        self._bytes = 0  # files on disk
        self._reserved = 0  # files being written
        self._warned = False

    @property
    def directory(self) -> Path | None:
        """This run's directory, None when publishing is off (or the directory could not be made)."""
        return self._dir

    @property
    def bytes(self) -> int:
        """Bytes of the grids' files on disk, and of those being written."""
        return self._bytes + self._reserved

    def open(self) -> None:
        """Remove what earlier runs left (those whose lock is free) and make this run's directory."""
        try:
            if self.root.is_dir():
                for old in self.root.iterdir():
                    _remove_unlocked(old)
            if self.max_bytes <= 0:
                with contextlib.suppress(OSError):
                    self.root.rmdir()
                return
            self.root.mkdir(parents=True, exist_ok=True)
            run = self.root / f"{os.getpid()}-{os.urandom(4).hex()}"
            run.mkdir()
            lock = (run / LOCK_NAME).open("wb")
        except OSError as exc:
            LOG.warning("cannot keep map grids for the planner workers in %s (%s): every plan ships its grid",
                        self.root, exc)
            return
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)  # a new file: nobody else holds it
        self._dir, self._lock = run, lock

    def close(self) -> None:
        """Delete every grid and this run's directory (the service stops; plans in flight are over)."""
        directory, self._dir = self._dir, None
        self._grids.clear()
        self._bytes = 0
        self._report()
        if directory is not None:
            shutil.rmtree(directory, ignore_errors=True)
            with contextlib.suppress(OSError):
                self.root.rmdir()  # unless another service on this data directory is using it
        if self._lock is not None:
            self._lock.close()
            self._lock = None

    # ------------------------------------------------------------ plans

    def lease(self, uid: int, version: int) -> Lease | None:
        """The published grid of this map version, held for a plan; None when it is not published."""
        grid = self._grids.get((uid, version))
        if grid is None or grid.retired:
            return None
        return self._hold(grid)

    async def publish(
        self, uid: int, version: int, risk: np.ndarray, observed: np.ndarray, resolution: float,
        origin: tuple[float, ...], current: Callable[[], bool],
    ) -> Lease | None:
        """Publish the arrays of this map version (unless a plan did already) and hold them for a plan.

        ``current()`` says whether this is still the map's version (checked once the files are
        written). None: not published (off, over the byte bound, or the directory refused the files);
        the caller ships the arrays instead.
        """
        key = (uid, version)
        pending = self._pending.get(key)
        if pending is not None:  # another plan is writing this very version: wait for it
            await asyncio.shield(pending)
        grid = self._grids.get(key)
        if grid is not None:
            return self._hold(grid)
        if self._dir is None:
            return None
        need = risk.nbytes + observed.nbytes + 2 * _HEADER_ROOM
        if not self._make_room(need):
            return None
        stem = self._dir / f"m{uid}-v{version}"
        ref = GridRef(f"{stem}.risk.npy", f"{stem}.observed.npy", float(resolution), tuple(float(v) for v in origin),
                      tuple(int(n) for n in risk.shape))
        done: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._pending[key] = done
        self._reserved += need
        self._report()
        write = asyncio.ensure_future(self._run(_write, ref, risk, observed))
        try:
            await asyncio.shield(write)
        except asyncio.CancelledError:  # the plan's request is gone; the thread still writes: clean up after it
            write.add_done_callback(lambda _: self._written(key, ref, need, write, done, keep=False))
            raise
        except Exception:  # noqa: BLE001 - _written reports it (OSError) or raises it again
            pass
        written = self._written(key, ref, need, write, done, keep=True)
        if written is None:
            return None
        grid = _Grid(key, ref, written, retired=not current())
        self._grids[key] = grid
        self._bytes += written
        self._report()
        return self._hold(grid)

    def _written(self, key: tuple[int, int], ref: GridRef, need: int, write: asyncio.Future[int],
                 done: asyncio.Future[None], *, keep: bool) -> int | None:
        """Once a write has ended: the files' bytes if they are to be kept (written, and this run still
        publishes), else None with the files removed. An error other than ``OSError`` is raised again (``keep``)."""
        self._reserved -= need
        del self._pending[key]
        done.set_result(None)
        self._report()
        error = write.exception()
        if error is None and keep and self._dir is not None:
            self._warned = False
            return int(write.result())
        _unlink(ref)
        if isinstance(error, OSError):
            if not self._warned:
                LOG.warning("cannot write a map grid for the planner workers (%s): plans ship their grids until it "
                            "works again", error)
                self._warned = True
        elif error is not None and keep:
            raise error
        return None

    def retire(self, uid: int, below: int | None = None) -> None:
        """A map's versions below ``below`` (all of them when None: the map is gone) are no longer planned on."""
        for grid in [g for g in self._grids.values() if g.key[0] == uid and (below is None or g.key[1] < below)]:
            grid.retired = True
            if grid.users == 0:
                self._delete(grid)

    # ------------------------------------------------------------ inside

    def _hold(self, grid: _Grid) -> Lease:
        grid.users += 1
        self._grids.move_to_end(grid.key)
        return Lease(self, grid)

    def _release(self, grid: _Grid) -> None:
        grid.users -= 1
        if grid.users == 0 and grid.retired:
            self._delete(grid)

    def _make_room(self, need: int) -> bool:
        """Delete unused grids, least recently used first, until ``need`` more bytes fit; False if they cannot."""
        if need > self.max_bytes:
            return False
        for grid in list(self._grids.values()):
            if self.bytes + need <= self.max_bytes:
                break
            if grid.users == 0:
                self._delete(grid)
        return self.bytes + need <= self.max_bytes

    def _delete(self, grid: _Grid) -> None:
        if grid.deleted:
            return
        grid.deleted = True
        self._grids.pop(grid.key, None)
        self._bytes -= grid.nbytes
        _unlink(grid.ref)
        self._report()

    def _report(self) -> None:
        if self._on_bytes is not None:
            self._on_bytes(self.bytes)


def _write(ref: GridRef, risk: np.ndarray, observed: np.ndarray) -> int:
    """Write the two files (in a thread); their size on disk. A failure leaves no file behind."""
    try:
        np.save(ref.risk_path, np.ascontiguousarray(risk), allow_pickle=False)
        np.save(ref.observed_path, np.ascontiguousarray(observed), allow_pickle=False)
        return os.path.getsize(ref.risk_path) + os.path.getsize(ref.observed_path)
    except BaseException:
        _unlink(ref)
        raise


def _unlink(ref: GridRef) -> None:
    for path in (ref.risk_path, ref.observed_path):
        with contextlib.suppress(FileNotFoundError):
            os.unlink(path)


def _remove_unlocked(run: Path) -> None:
    """Remove an earlier run's directory unless its service still holds its lock."""
    if not run.is_dir():
        run.unlink(missing_ok=True)
        return
    try:
        with (run / LOCK_NAME).open("rb") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except FileNotFoundError:
        pass  # killed before it took its lock, or a stray directory
    except BlockingIOError:
        return  # a live service
    shutil.rmtree(run, ignore_errors=True)


# ---------------------------------------------------------------- a worker's side


@dataclass(eq=False)
class _Field:
    field: Any  # planning.RiskField
    base: int  # bytes of its risk and observed arrays
    dilations: set[tuple[float, bool]] = field(default_factory=set)  # (radius, unknown mask too)

    @property
    def nbytes(self) -> int:
        per_radius = 2 * self.field.risk.nbytes  # the dilated risk (cost) and that of the observed cells (validity)
        unknown = self.field.observed.nbytes
        radii = {radius for radius, _ in self.dilations}
        masks = {radius for radius, with_unknown in self.dilations if with_unknown}
        return self.base + per_radius * len(radii) + unknown * len(masks)


class FieldCache:
    """A worker's ``RiskField`` per published grid, least recently used first out, within ``max_bytes``."""

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self._fields: OrderedDict[str, _Field] = OrderedDict()
        self.loads = 0  # fields built from files (for tests and logs)

    def __len__(self) -> int:
        return len(self._fields)

    @property
    def nbytes(self) -> int:
        """Bytes of the fields kept: their arrays and the dilations counted by ``used``."""
        return sum(f.nbytes for f in self._fields.values())

    @property
    def paths(self) -> list[str]:
        """The risk files of the grids whose fields are kept, least recently used first."""
        return list(self._fields)

    def field(self, ref: GridRef) -> Any:
        """The field of ``ref``: kept from an earlier plan, or read from its files (``OSError`` if they are gone)."""
        from planning import RiskField

        self._forget_gone(keep=ref.risk_path)
        kept = self._fields.get(ref.risk_path)
        if kept is not None:
            self._fields.move_to_end(ref.risk_path)
            return kept.field
        risk = np.load(ref.risk_path, mmap_mode="r", allow_pickle=False)
        observed = np.load(ref.observed_path, mmap_mode="r", allow_pickle=False)
        made = RiskField(risk, ref.resolution, ref.origin, observed=observed)  # copies: the files may go now
        del risk, observed
        self.loads += 1
        if self.max_bytes > 0:
            self._fields[ref.risk_path] = _Field(made, made.risk.nbytes + made.observed.nbytes)
            self._trim(keep=ref.risk_path)
        return made

    def used(self, ref: GridRef, robot_radius: float, allow_unknown: bool) -> None:
        """Count the dilations a plan on ``ref`` left cached on its field, then keep within the bound."""
        kept = self._fields.get(ref.risk_path)
        if kept is not None:
            kept.dilations.add((float(robot_radius), not allow_unknown))
            self._trim(keep=ref.risk_path)

    def _trim(self, keep: str) -> None:
        """Drop the least recently used fields until the bound holds; ``keep`` too, last, if alone it is over."""
        total = self.nbytes
        for path in [p for p in self._fields if p != keep] + [keep]:
            if total <= self.max_bytes:
                return
            total -= self._fields.pop(path).nbytes

    def _forget_gone(self, keep: str) -> None:
        """Drop the fields whose files are gone: a newer version or a deleted map; no plan can ask for them."""
        for path in [p for p in self._fields if p != keep and not os.path.exists(p)]:
            del self._fields[path]


_uids = itertools.count(1)


def new_uid() -> int:
    """A number that names one map held by this service process (a deleted map's never comes back)."""
    return next(_uids)

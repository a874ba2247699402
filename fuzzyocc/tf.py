"""Rigid transforms between named frames over time: what tf2 does for a recorded bag, with scipy's rotations.

A :class:`TransformBuffer` takes the samples of ``/tf`` (dynamic) and ``/tf_static`` (static) as
plain numbers (parent frame, child frame, stamp in nanoseconds, translation, quaternion) and
answers ``T_target_source`` at any stamp: along the chain of frames from ``source`` up to the
nearest frame it shares with ``target`` and down again, each dynamic edge interpolated at the stamp
(translation linearly, rotation by scipy's ``Slerp``, the shorter way round as tf2 does), the edges
composed with scipy's ``Rotation``. A stamp outside an edge's samples is not extrapolated: the
lookup fails with a :class:`LookupFailed` whose ``reason`` is short and countable ("before the
first transform odom -> base_link").

The same rule serves a whole track at once (:func:`interpolate`, which :mod:`fuzzyocc.trajectory`
uses), and the planar reading of a rotation lives here too: :func:`level_heading` (a level scanner's yaw)
and :func:`yaw_quaternion` (a yaw as a quaternion).

Quaternions are ``[x, y, z, w]`` (ROS order). Frames in names: ``T_a_b`` maps points of frame
``b`` into frame ``a`` (``p_a = T_a_b * p_b``). Nothing here knows of ROS messages or the web.
"""

from __future__ import annotations

import math
from bisect import bisect_left
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

#: Longest chain of frames a lookup follows (a cycle in a broken tree stops here, not in a loop).
MAX_CHAIN = 64

#: How far a quaternion's norm may be from 1 for it to count as a unit quaternion: a sensor pose in, a
#: trajectory's poses. Loose enough for float32 messages and JSON written to a few digits, as tf2 and ROS
#: take them; tighter than anything that is not meant to be a rotation.
UNIT_QUATERNION_TOLERANCE = 1e-3

#: A scanner whose z axis is farther than this from the vertical (up or down) is not level: a 2-D map refuses
#: its LaserScan (3 degrees: a beam 10 m out is then at most 0.5 m off the map's plane).
LEVEL_TOLERANCE_RAD = math.radians(3.0)


class NotLevel(ValueError):
    """A scanner tilted more than ``LEVEL_TOLERANCE_RAD`` from level; ``degrees`` says how far."""

    def __init__(self, degrees: float, index: int | None = None) -> None:
        where = "" if index is None else f"pose {index}: "
        super().__init__(f"{where}the scanner is tilted {degrees:.1f} degrees from level (its z axis against the "
                         f"vertical), more than {math.degrees(LEVEL_TOLERANCE_RAD):g}")
        self.degrees = degrees
        self.index = index

    def __reduce__(self) -> tuple[type[NotLevel], tuple[float, int | None]]:
        return NotLevel, (self.degrees, self.index)  # its message is made of these: a process's refusal unpickles


def level_heading(quaternion_xyzw: object) -> tuple[float, float]:
    """(theta, turn) of a level scanner rotated by ``quaternion_xyzw`` (normalised here): the heading of its x axis
    in the parent's xy plane (radians, REP 103, in [-pi, pi]), and +1 (z up) or -1 (z down: it sweeps the other
    way). Roll and pitch within ``LEVEL_TOLERANCE_RAD`` are dropped; beyond it, :class:`NotLevel`."""
    try:
        thetas, turns = level_headings(np.reshape(np.asarray(quaternion_xyzw, dtype=np.float64), (1, 4)))
    except NotLevel as exc:
        raise NotLevel(exc.degrees) from None
    return float(thetas[0]), float(turns[0])


def level_headings(quaternions_xyzw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`level_heading` of each row of an ``(N, 4)`` array, by the same arithmetic (one pose gets the same bits
    either way): thetas and turns; :class:`NotLevel` naming the first row tilted off level."""
    q = np.asarray(quaternions_xyzw, dtype=np.float64).reshape(-1, 4)
    q = q / np.sqrt(np.sum(q * q, axis=1))[:, None]
    qx, qy, qz, qw = q.T
    up = 1.0 - 2.0 * (qx * qx + qy * qy)  # z of the scanner's z axis in the parent frame
    tilted = np.flatnonzero(np.abs(up) < math.cos(LEVEL_TOLERANCE_RAD))
    if tilted.size:
        i = int(tilted[0])
        raise NotLevel(math.degrees(math.acos(min(abs(float(up[i])), 1.0))), index=i)
    theta = np.arctan2(2.0 * (qx * qy + qw * qz), 1.0 - 2.0 * (qy * qy + qz * qz))
    return theta, np.where(up > 0.0, 1.0, -1.0)


def yaw_quaternion(yaw: float) -> tuple[float, float, float, float]:
    """``[x, y, z, w]`` of a rotation by ``yaw`` about +z (REP 103: counter-clockwise from +x)."""
    return 0.0, 0.0, math.sin(0.5 * yaw), math.cos(0.5 * yaw)


def nanoseconds_since_first(stamps_ns: np.ndarray) -> np.ndarray:
    """Integer stamps as float64 nanoseconds since the first: exact for 104 days (since the epoch, float64 would
    round a stamp to 256 ns). What a :class:`Slerp` over a track is built on."""
    return (np.asarray(stamps_ns, dtype=np.int64) - int(stamps_ns[0])).astype(np.float64)


def interpolate(stamps_ns: np.ndarray, translations: np.ndarray, slerp: Slerp,
                at_ns: np.ndarray) -> tuple[np.ndarray, Rotation]:
    """A track's poses at stamps strictly between its first and last sample, as tf2 interpolates them.

    Parameters
    ----------
    stamps_ns : (N,) ndarray of int64
        The samples' stamps, strictly increasing, N >= 2.
    translations : (N, 3) ndarray of float64
        The samples' translations.
    slerp : Slerp
        The samples' rotations over :func:`nanoseconds_since_first` of ``stamps_ns``.
    at_ns : (M,) ndarray of int64
        The stamps asked for, each inside ``(stamps_ns[0], stamps_ns[-1])``.

    Returns
    -------
    (M, 3) ndarray of float64, Rotation of M
        The translation linearly between the two samples around each stamp, and the rotation by
        slerp, the shorter way round. A stamp equal to a sample's gives that sample's pose up to
        rounding: a caller that wants it exactly takes the sample.
    """
    after = np.searchsorted(stamps_ns, at_ns, side="right")
    before = after - 1
    # int64 differences, exact as float64 below 2**53 ns: the fraction is the correctly rounded quotient
    u = (at_ns - stamps_ns[before]).astype(np.float64) / (stamps_ns[after] - stamps_ns[before]).astype(np.float64)
    a, b = translations[before], translations[after]
    return a + u[:, None] * (b - a), slerp((at_ns - stamps_ns[0]).astype(np.float64))


@dataclass(frozen=True)
class Transform:
    """A rigid transform ``T_parent_child``: rotate by ``rotation``, then translate by ``translation`` (metres)."""

    translation: np.ndarray
    rotation: Rotation

    @classmethod
    def of(cls, translation: object, rotation_xyzw: object) -> Transform:
        """From numbers, checked finite; the quaternion ``[x, y, z, w]`` is normalised."""
        t = np.array(translation, dtype=np.float64).reshape(3)
        q = np.array(rotation_xyzw, dtype=np.float64).reshape(4)
        if not (np.isfinite(t).all() and np.isfinite(q).all()):
            raise ValueError(f"transform must be finite, got translation {t.tolist()}, rotation {q.tolist()}")
        norm = float(np.linalg.norm(q))
        if norm < 1e-9:  # scipy refuses only an exact zero; a quaternion this short has no direction to trust
            raise ValueError(f"quaternion {q.tolist()} has no direction (norm {norm})")
        return cls(t, Rotation.from_quat(q))

    @classmethod
    def identity(cls) -> Transform:
        return cls(np.zeros(3), Rotation.identity())

    def __mul__(self, other: Transform) -> Transform:
        """``T_a_b * T_b_c = T_a_c``."""
        return Transform(self.translation + self.rotation.apply(other.translation), self.rotation * other.rotation)

    def inverse(self) -> Transform:
        inverse = self.rotation.inv()
        return Transform(-inverse.apply(self.translation), inverse)


class LookupFailed(LookupError):
    """No transform at that stamp; ``reason`` is short and the same for every stamp that fails alike."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


@dataclass
class _Track:
    """The samples of one dynamic edge ``parent -> child``, sorted by stamp and interpolated when first looked up."""

    parent: str
    stamps: list[int] = field(default_factory=list)
    transforms: list[Transform] = field(default_factory=list)
    _slerp: Slerp | None = None
    _stamps: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    _translations: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    _ready: bool = True

    def add(self, stamp_ns: int, transform: Transform) -> None:
        self.stamps.append(stamp_ns)
        self.transforms.append(transform)
        self._ready = False

    def _prepare(self) -> None:
        # stable: of two samples with one stamp the later-recorded wins, as in tf2's cache
        order = sorted(range(len(self.stamps)), key=self.stamps.__getitem__)
        stamps = [self.stamps[i] for i in order]
        transforms = [self.transforms[i] for i in order]
        keep = [i for i in range(len(stamps)) if i + 1 == len(stamps) or stamps[i + 1] != stamps[i]]
        self.stamps = [stamps[i] for i in keep]
        self.transforms = [transforms[i] for i in keep]
        self._stamps = np.array(self.stamps, dtype=np.int64)
        self._translations = np.array([t.translation for t in self.transforms], dtype=np.float64)
        self._slerp = (Slerp(nanoseconds_since_first(self._stamps),
                             Rotation.concatenate([t.rotation for t in self.transforms]))
                       if len(self.stamps) > 1 else None)
        self._ready = True

    def at(self, stamp_ns: int, child: str) -> Transform:
        """The sample at ``stamp_ns``, or the two around it interpolated (translation linearly, rotation by slerp)."""
        if not self._ready:
            self._prepare()
        stamps = self.stamps
        i = bisect_left(stamps, stamp_ns)
        if i < len(stamps) and stamps[i] == stamp_ns:
            return self.transforms[i]
        if i == 0:
            raise LookupFailed(f"before the first transform {self.parent} -> {child}")
        if i == len(stamps):
            raise LookupFailed(f"after the last transform {self.parent} -> {child}")
        assert self._slerp is not None  # two samples at least, one either side
        translation, rotation = interpolate(self._stamps, self._translations, self._slerp,
                                            np.array([stamp_ns], dtype=np.int64))
        return Transform(translation[0], rotation[0])

    @property
    def span(self) -> tuple[int, int]:
        if not self._ready:
            self._prepare()
        return self.stamps[0], self.stamps[-1]


class TransformBuffer:
    """Transforms between frames over time, filled from a recording and then looked up (tf2's ``Buffer``).

    Each child frame has one parent (a tree, as in tf2): a dynamic sample for a child already
    known under another parent is ignored and counted in ``ignored``. A child with dynamic samples
    ignores its static transform (tf2 keeps only the latest data for a frame).
    """

    def __init__(self) -> None:
        self._static: dict[str, tuple[str, Transform]] = {}
        self._dynamic: dict[str, _Track] = {}
        self.ignored = 0

    @staticmethod
    def _frame(name: str) -> str:
        return name.lstrip("/")  # tf1's "/base_link" is tf2's "base_link"

    def add(self, parent: str, child: str, stamp_ns: int, transform: Transform, *, static: bool = False) -> None:
        """Record ``T_parent_child`` at ``stamp_ns`` (ignored for a static transform)."""
        parent, child = self._frame(parent), self._frame(child)
        if not parent or not child or parent == child:
            self.ignored += 1
            return
        if static:
            self._static[child] = (parent, transform)
            return
        track = self._dynamic.get(child)
        if track is None:
            track = self._dynamic[child] = _Track(parent)
        elif track.parent != parent:
            self.ignored += 1
            return
        track.add(int(stamp_ns), transform)

    def frames(self) -> set[str]:
        """Every frame named by a transform."""
        names = set(self._static) | set(self._dynamic)
        names |= {p for p, _ in self._static.values()} | {t.parent for t in self._dynamic.values()}
        return names

    def span(self, child: str) -> tuple[int, int] | None:
        """First and last stamp of the dynamic edge into ``child``, or None (static or unknown)."""
        track = self._dynamic.get(self._frame(child))
        return track.span if track else None

    def _parent(self, child: str) -> str | None:
        if child in self._dynamic:
            return self._dynamic[child].parent
        if child in self._static:
            return self._static[child][0]
        return None

    def _edge(self, child: str, stamp_ns: int) -> Transform:
        track = self._dynamic.get(child)
        if track is not None:
            return track.at(stamp_ns, child)
        return self._static[child][1]

    def _chain(self, frame: str) -> list[str]:
        """``frame``, its parent, its grandparent ... up to the root of its tree."""
        chain = [frame]
        while (parent := self._parent(chain[-1])) is not None:
            if parent in chain or len(chain) > MAX_CHAIN:
                raise LookupFailed(f"the transform tree above {frame} has a cycle or is deeper than {MAX_CHAIN}")
            chain.append(parent)
        return chain

    def _down(self, chain: list[str], stamp_ns: int) -> Transform | None:
        """``T_top_bottom`` along a chain listed bottom first; None for a chain of one frame (the identity).

        The edges are looked up from the top (a failure names the highest edge that fails, as it always
        has), then composed from the bottom up, as a point is carried; with nothing for the identity:
        each of scipy's calls costs tens of microseconds.
        """
        edges = [self._edge(child, stamp_ns) for child in reversed(chain[:-1])]
        out = edges.pop() if edges else None
        while edges:
            out = edges.pop() * out
        return out

    def lookup(self, target: str, source: str, stamp_ns: int) -> Transform:
        """``T_target_source`` at ``stamp_ns`` (nanoseconds); :class:`LookupFailed` says why not."""
        target, source = self._frame(target), self._frame(source)
        if target == source:
            return Transform.identity()
        up_source, up_target = self._chain(source), self._chain(target)
        common = next((f for f in up_source if f in set(up_target)), None)
        if common is None:
            raise LookupFailed(f"no chain of transforms from {source or '(empty frame_id)'} to {target}")
        below_source = up_source[:up_source.index(common) + 1]
        below_target = up_target[:up_target.index(common) + 1]
        T_common_source = self._down(below_source, stamp_ns) or Transform.identity()
        T_common_target = self._down(below_target, stamp_ns)
        return T_common_source if T_common_target is None else T_common_target.inverse() * T_common_source

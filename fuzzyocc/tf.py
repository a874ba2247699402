"""Rigid transforms between named frames over time: what tf2 does for a recorded bag, in numpy.

A :class:`TransformBuffer` takes the samples of ``/tf`` (dynamic) and ``/tf_static`` (static) as
plain numbers (parent frame, child frame, stamp in nanoseconds, translation, quaternion) and
answers ``T_target_source`` at any stamp: along the chain of frames from ``source`` up to the
nearest frame it shares with ``target`` and down again, each dynamic edge interpolated at the stamp
(translation linearly, rotation by slerp, as tf2 does), the edges composed. A stamp outside an
edge's samples is not extrapolated: the lookup fails with a :class:`LookupFailed` whose ``reason``
is short and countable ("before the first transform odom -> base_link").

Quaternions are ``[x, y, z, w]`` (ROS order). Frames in names: ``T_a_b`` maps points of frame
``b`` into frame ``a`` (``p_a = T_a_b * p_b``). Nothing here knows of ROS messages or the web.
"""

from __future__ import annotations

from bisect import bisect_left
from dataclasses import dataclass, field

import numpy as np

#: Longest chain of frames a lookup follows (a cycle in a broken tree stops here, not in a loop).
MAX_CHAIN = 64
#: Below this angle between two rotations slerp degenerates; linear interpolation (then normalised) is exact enough.
_SLERP_LINEAR_BELOW = 1e-6


def _unit(q: np.ndarray) -> np.ndarray:
    norm = float(np.sqrt(q @ q))
    if not np.isfinite(norm) or norm < 1e-9:
        raise ValueError(f"quaternion {q.tolist()} has no direction (norm {norm})")
    return q / norm


def quaternion_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a * b`` of ``[x, y, z, w]`` quaternions (apply ``b`` first, then ``a``)."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array([
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    ])


def rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The vector ``v`` (3,) rotated by the unit quaternion ``q``."""
    u, w = q[:3], q[3]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def slerp(q0: np.ndarray, q1: np.ndarray, u: float) -> np.ndarray:
    """Spherical linear interpolation between unit quaternions, the shorter way round (``u`` in [0, 1])."""
    dot = float(q0 @ q1)
    if dot < 0.0:  # q and -q are the same rotation: take the one on q0's side
        q1, dot = -q1, -dot
    angle = float(np.arccos(min(dot, 1.0)))
    if angle < _SLERP_LINEAR_BELOW:
        return _unit(q0 + u * (q1 - q0))
    s = np.sin(angle)
    return _unit((np.sin((1.0 - u) * angle) / s) * q0 + (np.sin(u * angle) / s) * q1)


@dataclass(frozen=True)
class Transform:
    """A rigid transform ``T_parent_child``: rotate by ``rotation`` (unit ``[x, y, z, w]``), then translate."""

    translation: np.ndarray
    rotation: np.ndarray

    @classmethod
    def of(cls, translation: object, rotation_xyzw: object) -> Transform:
        """From numbers, checked finite; the quaternion is normalised."""
        t = np.array(translation, dtype=np.float64).reshape(3)
        q = np.array(rotation_xyzw, dtype=np.float64).reshape(4)
        if not (np.isfinite(t).all() and np.isfinite(q).all()):
            raise ValueError(f"transform must be finite, got translation {t.tolist()}, rotation {q.tolist()}")
        return cls(t, _unit(q))

    @classmethod
    def identity(cls) -> Transform:
        return cls(np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]))

    def __mul__(self, other: Transform) -> Transform:
        """``T_a_b * T_b_c = T_a_c``."""
        return Transform(self.translation + rotate(self.rotation, other.translation),
                         _unit(quaternion_multiply(self.rotation, other.rotation)))

    def inverse(self) -> Transform:
        conjugate = self.rotation * np.array([-1.0, -1.0, -1.0, 1.0])
        return Transform(-rotate(conjugate, self.translation), conjugate)


def interpolate(a: Transform, b: Transform, u: float) -> Transform:
    """The transform a fraction ``u`` of the way from ``a`` to ``b``: translation linear, rotation slerp."""
    return Transform(a.translation + u * (b.translation - a.translation), slerp(a.rotation, b.rotation, u))


class LookupFailed(LookupError):
    """No transform at that stamp; ``reason`` is short and the same for every stamp that fails alike."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


@dataclass
class _Track:
    """The samples of one dynamic edge ``parent -> child``, sorted by stamp when first looked up."""

    parent: str
    stamps: list[int] = field(default_factory=list)
    transforms: list[Transform] = field(default_factory=list)
    _sorted: bool = True

    def add(self, stamp_ns: int, transform: Transform) -> None:
        if self.stamps and stamp_ns < self.stamps[-1]:
            self._sorted = False
        self.stamps.append(stamp_ns)
        self.transforms.append(transform)

    def _sort(self) -> None:
        # stable: of two samples with one stamp the later-recorded wins, as in tf2's cache
        order = sorted(range(len(self.stamps)), key=self.stamps.__getitem__)
        stamps = [self.stamps[i] for i in order]
        transforms = [self.transforms[i] for i in order]
        keep = [i for i in range(len(stamps)) if i + 1 == len(stamps) or stamps[i + 1] != stamps[i]]
        self.stamps = [stamps[i] for i in keep]
        self.transforms = [transforms[i] for i in keep]
        self._sorted = True

    def at(self, stamp_ns: int, child: str) -> Transform:
        if not self._sorted:
            self._sort()
        stamps = self.stamps
        i = bisect_left(stamps, stamp_ns)
        if i < len(stamps) and stamps[i] == stamp_ns:
            return self.transforms[i]
        if i == 0:
            raise LookupFailed(f"before the first transform {self.parent} -> {child}")
        if i == len(stamps):
            raise LookupFailed(f"after the last transform {self.parent} -> {child}")
        t0, t1 = stamps[i - 1], stamps[i]
        return interpolate(self.transforms[i - 1], self.transforms[i], (stamp_ns - t0) / (t1 - t0))

    @property
    def span(self) -> tuple[int, int]:
        if not self._sorted:
            self._sort()
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

    def _down(self, chain: list[str], stamp_ns: int) -> Transform:
        """``T_top_bottom`` along a chain listed bottom first."""
        out = Transform.identity()
        for child in reversed(chain[:-1]):
            out = out * self._edge(child, stamp_ns)
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
        T_common_source = self._down(below_source, stamp_ns)
        T_common_target = self._down(below_target, stamp_ns)
        return T_common_target.inverse() * T_common_source

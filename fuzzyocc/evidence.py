"""The shipped default engine, ``evidence``: Payeur's inference with labels that count evidence.

Still the paper's engine (labels, piecewise-linear membership functions, a Mamdani rule table
with min/max, centroid defuzzification); what changes is what the labels mean, tuned on the
recorded logs of real buildings (``bench/bench_maps.py``, figures in ``docs/DESIGN.md`` and
``bench/README.md``):

- **Eleven state labels are levels of evidence**: ``E5 .. E1`` (five levels of "seen empty"),
  ``UNK``, ``O1 .. O5`` (five levels of "seen occupied"), risk ``0.033, 0.1 .. 0.9, 0.967``
  (:func:`fuzzyocc.engine.even_output_mfs`). A cell one level above ``UNK`` is at risk 0.6, the
  planner's default ``max_risk``: what a default plan refuses.
- **The rule table counts**: a measurement of the surface (``O*`` evidence) raises a cell two
  levels, free space (``E*``) lowers it one, ``UNK`` (behind the surface) leaves it alone,
  clamped at the ends. Two to one is OctoMap's own ratio (log-odds +0.85 / -0.41), and five
  levels above unknown make a wall survive five grazing beams in a row, as OctoMap's clamping
  does (Table 1 took a wall to ``UNK`` on one free reading: walls wore away on long logs). An
  obstacle seen three times in unknown space and gone is cleared by the fifth scan (OctoMap:
  the seventh).
- **A no-return is read in context** (``no_return_neighbours``): one with a hit among its three
  neighbours on each side most likely met the same dark or glass surface they did, so it
  clears free space only up to 0.1 m before the nearest of those hits; a no-return among
  no-returns (open space) clears on to ``range_max``. Clearing every no-return to
  ``range_max`` wore walls away on logs with many (csail, edmonton, freiburg: 1-3 points of
  held-out beams lost); never letting them lower occupied cells kept a left obstacle forever
  when open space lay behind it. (ROS consumers of LaserScans, ``laser_geometry`` and Nav2's
  ``inf_is_valid: false``, do not clear on no-returns at all.) Input label ``E5`` is where
  no-returns fall (below :data:`fuzzyocc.raycast.NO_RETURN_DISTANCE` / 4, where no hit
  lands); in this table it concludes what ``E4`` does.
- **Input functions tight around the surface**, in sigmas: ``E*`` up to -0.45 sigma, the
  surface band ``O*`` from -0.2 to +1.05, ``UNK`` from +1.55, so a cell in front of the measured
  surface is not marked occupied (Table 1's PO/MPO memberships thickened walls by a cell).
- **Grazing beams** (``incidence_floor``): sigma along a beam is divided by the sine of its
  incidence on the surface (at least 0.3), so a grazing beam's evidence spreads along the wall
  instead of clearing the wall's cells in front of its end point.

The paper's engine stays available as the preset ``paper`` (:meth:`FuzzyEngine.paper`).
"""

from __future__ import annotations

from fuzzyocc.engine import FuzzyEngine, even_output_mfs
from fuzzyocc.membership import LeftShoulder, MembershipFunction, RightShoulder, Trapezoid, Triangle
from fuzzyocc.raycast import NO_RETURN_DISTANCE

__all__ = ["EVIDENCE_LABELS", "evidence_engine"]

LEVELS = 5
EVIDENCE_LABELS: tuple[str, ...] = (
    *(f"E{k}" for k in range(LEVELS, 0, -1)), "UNK", *(f"O{k}" for k in range(1, LEVELS + 1))
)
HIT_STEP = 2
MISS_STEP = 1

#: Where the input functions change, in sigmas from the measured surface (tuned on the logs).
FREE_UNTIL = -0.45  # E1's peak: free space up to here
SURFACE_FROM = -0.2  # O1's peak: the surface band starts here
SURFACE_UNTIL = 1.05  # O5's peak: the band ends here
UNKNOWN_FROM = 1.55  # UNK's plateau: the cells behind the surface are left alone
INCIDENCE_FLOOR = 0.3
NO_RETURN_NEIGHBOURS = 3
#: Peaks of E4, E3, E2 (free space far in front; their conclusions are E1's, see below).
FAR_FREE = (-5.5, -4.5, -3.5)


def _inputs() -> dict[str, MembershipFunction]:
    no_return_end = NO_RETURN_DISTANCE / 2  # only a no-return's cells lie below this
    e4, e3, e2 = FAR_FREE
    o = [SURFACE_FROM + (SURFACE_UNTIL - SURFACE_FROM) * k / (LEVELS - 1) for k in range(LEVELS)]
    return {
        "E5": LeftShoulder(no_return_end, no_return_end / 2),
        "E4": Trapezoid(no_return_end, no_return_end / 2, e4, e3),
        "E3": Triangle(e4, e3, e2),
        "E2": Triangle(e3, e2, FREE_UNTIL),
        "E1": Triangle(e2, FREE_UNTIL, o[0]),
        "O1": Triangle(FREE_UNTIL, o[0], o[1]),
        "O2": Triangle(o[0], o[1], o[2]),
        "O3": Triangle(o[1], o[2], o[3]),
        "O4": Triangle(o[2], o[3], o[4]),
        "O5": Triangle(o[3], o[4], UNKNOWN_FROM),
        "UNK": RightShoulder(o[4], UNKNOWN_FROM),
    }


def _step(evidence: str) -> int:
    """Levels a cell moves on ``evidence``, whatever its state (clamped at the ends by the caller)."""
    if evidence == "UNK":
        return 0  # behind the surface: nothing was measured there
    if evidence.startswith("O"):
        return HIT_STEP
    return -MISS_STEP


def _rules() -> dict[str, dict[str, str]]:
    top = len(EVIDENCE_LABELS) - 1
    return {
        state: {
            evidence: EVIDENCE_LABELS[min(top, max(0, EVIDENCE_LABELS.index(state) + _step(evidence)))]
            for evidence in EVIDENCE_LABELS
        }
        for state in EVIDENCE_LABELS
    }


def evidence_engine() -> FuzzyEngine:
    """The ``evidence`` preset: 11 labels, counting rule table, min/max, centroid (see the module doc)."""
    return FuzzyEngine(
        labels=EVIDENCE_LABELS,
        unknown="UNK",
        input_mfs=_inputs(),  # type: ignore[arg-type]  # normalised in __post_init__
        output_mfs=even_output_mfs(EVIDENCE_LABELS),  # type: ignore[arg-type]
        rules=_rules(),  # type: ignore[arg-type]
        incidence_floor=INCIDENCE_FLOOR,
        no_return_neighbours=NO_RETURN_NEIGHBOURS,
    )

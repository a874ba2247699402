"""``plan``'s parameters: the defaults of those a caller may leave out, and each number's range whatever the map.

``plan`` checks its arguments against these ranges, and some of them against what the map makes
sensible too (the robot radius, the goal tolerance and the turning radius against the map's size,
the risk weight against ``MAX_RISK_WEIGHT``). The service's plan request declares the same ranges
(``app.schemas.plans``): a request outside them is refused before it reaches a planner, and the
OpenAPI document shows them. It imports no other module of ``planning``, so that any of them may
import it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Number:
    """``plan``'s parameter ``name``: a finite number above ``low`` (or from it, unless ``low_open``) up to ``high``."""

    name: str
    low: float
    low_open: bool = False
    high: float = math.inf

    def check(self, value: Any, high: float = math.inf) -> float:
        """``value`` as a float in the range, and at most ``high`` (a bound the map sets); ValueError naming it."""
        high = min(high, self.high)
        try:
            x = float(value)
        except (TypeError, ValueError):
            raise ValueError(f"{self.name}: must be a number, got {value!r}") from None
        if not math.isfinite(x) or x < self.low or (self.low_open and x == self.low) or x > high:
            bound = f"> {self.low}" if self.low_open else f">= {self.low}"
            if high < math.inf:
                bound += f" and <= {high}"
            raise ValueError(f"{self.name}: must be a finite number {bound}, got {value!r}")
        return x


TIME_LIMIT = Number("time_limit", 0.0, low_open=True)
ROBOT_RADIUS = Number("robot_radius", 0.0)
MAX_RISK = Number("max_risk", 0.0, high=1.0)
RISK_WEIGHT = Number("risk_weight", 0.0)
GOAL_TOLERANCE = Number("goal_tolerance", 0.0, low_open=True)
TURNING_RADIUS = Number("turning_radius", 0.0, low_open=True)
#: The seeds OMPL takes (``plan`` shifts them by one: OMPL refuses 0).
SEEDS = range(2**32)

#: The defaults of ``plan`` and of the service's plan request (``max_risk``'s: ``planning.field.DEFAULT_MAX_RISK``).
DEFAULT_PLANNER = "RRTstar"
DEFAULT_TIME_LIMIT = 1.0
DEFAULT_ROBOT_RADIUS = 0.2
DEFAULT_RISK_WEIGHT = 1.0
DEFAULT_ALLOW_UNKNOWN = True

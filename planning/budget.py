"""How long a plan may take by the clock (no OMPL import: a service's event loop reads it)."""

from __future__ import annotations

#: A seeded plan's wall-clock bound, in multiples of its ``time_limit``: its iteration budget,
#: sized to fit ``time_limit`` on an idle machine, ends it first unless the machine is loaded.
SEEDED_CLOCK_FACTOR = 3.0


def wall_clock_limit(time_limit: float, seeded: bool) -> float:
    """Seconds a plan may take by the clock: ``time_limit``, or ``SEEDED_CLOCK_FACTOR`` times it when seeded.

    (Plus the one-time warm-up of a process's first plan in a state space, see
    ``planning.warming``.) A service that waits for a plan in another process uses it to tell
    a slow plan from a stuck one.
    """
    return time_limit * (SEEDED_CLOCK_FACTOR if seeded else 1.0)

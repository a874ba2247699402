"""Risk-aware path planning with OMPL on a risk grid.

```python
from planning import RiskField, plan, PlanError, PlanResult, available_planners
field = RiskField(risk, resolution=0.05, origin=(0.0, 0.0), observed=mask)
result = plan(field, start=(x, y), goal=(x, y), planner="RRTstar", robot_radius=0.2, max_risk=0.45)
check = check_path(field, result.path, robot_radius=0.2, max_risk=0.45)  # later, on a newer field
```

Knows nothing of fuzzy labels or HTTP: a risk grid in, a path out.

``plan``, ``check_path``, ``warm_up``, ``quiet_ompl`` and ``STATE_SPACES`` are imported at their first use: the
modules behind them compile numba kernels as they are imported (seconds on a cold cache), which a
process that only names planners and state spaces (the service's web process: plans run in its
worker processes) should not pay for.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from planning.budget import wall_clock_limit
from planning.field import DEFAULT_MAX_RISK, RiskField
from planning.planners import STATE_SPACE_NAMES, available_planners
from planning.result import PLAN_ERROR_CODES, PathCheck, PlanError, PlanResult

if TYPE_CHECKING:
    from planning.ompl_solve import quiet_ompl
    from planning.path_check import check_path
    from planning.query import plan
    from planning.spaces import STATE_SPACES
    from planning.warming import warm_up

__all__ = [
    "DEFAULT_MAX_RISK",
    "PathCheck",
    "PLAN_ERROR_CODES",
    "STATE_SPACES",
    "STATE_SPACE_NAMES",
    "PlanError",
    "PlanResult",
    "RiskField",
    "available_planners",
    "check_path",
    "plan",
    "quiet_ompl",
    "wall_clock_limit",
    "warm_up",
]

_LAZY = {"plan": "planning.query", "quiet_ompl": "planning.ompl_solve", "warm_up": "planning.warming",
         "STATE_SPACES": "planning.spaces", "check_path": "planning.path_check"}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'planning' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))

"""Risk-aware path planning with OMPL on a risk grid.

```python
from planning import RiskField, plan, PlanError, PlanResult, available_planners
field = RiskField(risk, resolution=0.05, origin=(0.0, 0.0), observed=mask)
result = plan(field, start=(x, y), goal=(x, y), planner="RRTstar", robot_radius=0.2, max_risk=0.6)
```

Knows nothing of fuzzy labels or HTTP: a risk grid in, a path out.
"""

from planning.field import RiskField
from planning.planners import available_planners
from planning.query import plan, quiet_ompl, warm_up
from planning.result import PLAN_ERROR_CODES, PlanError, PlanResult
from planning.spaces import STATE_SPACES

__all__ = [
    "PLAN_ERROR_CODES",
    "STATE_SPACES",
    "PlanError",
    "PlanResult",
    "RiskField",
    "available_planners",
    "plan",
    "quiet_ompl",
    "warm_up",
]

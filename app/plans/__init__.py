"""Plans on a map's risk: ``service.MapPlans`` checks a request and publishes the map's grid at one version,
``pool.PlanPool`` queues plans fairly by map over worker processes, and ``worker`` is what runs in them
(``planning.plan`` on the published grid). OMPL holds the GIL for a whole solve: no plan runs in the server."""

__all__ = ["pool", "service", "worker"]

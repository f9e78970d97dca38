"""Models of what the sensors see and how the vehicles move: measurement functions and
their Jacobians (:mod:`.measurements`), systematic errors of the stations
(:mod:`.systematic`) and the vehicle dynamics the simulator flies (:mod:`.dynamics`)."""

__all__: list[str] = []

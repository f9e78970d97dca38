"""Scenario files and what they simulate: the file schema (:mod:`.scenario_schema`),
loading and validation (:mod:`.scenario`), the simulator (:mod:`.simulator`) and the
time-ordered event stream the simulator nodes and the bag writer publish
(:mod:`.stream`)."""

__all__: list[str] = []

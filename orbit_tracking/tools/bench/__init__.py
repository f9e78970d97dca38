"""The benchmark suites of ``orbit-tracking bench``: triangulation (:mod:`.triangulation`),
the window estimator against its baselines (:mod:`.estimator`), station biases
(:mod:`.biases`) and the live nodes over DDS (:mod:`.dds`)."""

__all__: list[str] = []

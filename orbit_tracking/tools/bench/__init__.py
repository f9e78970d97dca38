"""The benchmark suites of ``orbit-tracking bench``: triangulation (:mod:`.triangulation`),
the window estimator against its baselines (:mod:`.estimator`), station biases
(:mod:`.biases`), the live nodes over DDS (:mod:`.dds`), fault injection (:mod:`.faults`)
and randomised draws against their own Cramér–Rao bound (:mod:`.robustness`, issue 14)."""

__all__: list[str] = []

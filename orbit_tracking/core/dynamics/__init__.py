"""Trajectory models with dynamics (seed 003): a rocket-equation flight fitted to the raw
measurements (:mod:`.rocket`, :mod:`.fit`), and how well its parameters are known
(:mod:`.observability`)."""

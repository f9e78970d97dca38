"""Methods we compare against in the benchmarks, not used by the nodes: an iterated EKF
with an RTS smoother (:mod:`.kalman`)."""

__all__: list[str] = []

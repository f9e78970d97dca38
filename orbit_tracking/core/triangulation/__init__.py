"""Position fixes from lines of sight: alignment of unsynchronised station streams onto
common epochs (:mod:`.alignment`), the weighted N-line intersection with its covariance and
quality gates (:mod:`.intersection`), and the pipeline the node and the offline tool share
(:mod:`.pipeline`)."""

__all__: list[str] = []

"""The data every path shares, simulated or real: measurement and state tables
(:mod:`.tables`), a window's observations (:mod:`.observations`), the nodes' time-ordered
buffer (:mod:`.buffer`) and station pose tracks (:mod:`.poses`). Nothing here imports the
simulator."""

__all__: list[str] = []

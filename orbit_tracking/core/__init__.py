"""ROS-free numerical core: pure numpy, scipy and cvxpy, deterministic (randomness through
numpy Generators, time as float seconds). Nothing here imports ``rclpy``, a message package
or the tools; test/test_layout.py checks it.

Shared basics sit at this level (:mod:`.frames`, :mod:`.time`, :mod:`.errors`,
:mod:`.schema`, :mod:`.metrics`); each method has a subpackage:

* :mod:`.models`: measurement models, systematic errors, vehicle dynamics for truth;
* :mod:`.data`: measurement tables, observations, buffers, station pose tracks (never the
  simulator);
* :mod:`.sim`: scenario files, the simulator, the event stream;
* :mod:`.triangulation`: alignment, line-of-sight intersection, gates (seed 003's fixes);
* :mod:`.estimation`: B-spline, knots, the Gauss-Newton window problem, biases, windows and
  stitching (seed 000);
* :mod:`.baselines`: the comparison methods of the benchmarks (KF + RTS smoother).
"""

__all__: list[str] = []

"""Seed 000's trajectory estimation on windows of raw measurements.

* :mod:`.bspline`, :mod:`.coverage`: the spline trajectory, incomplete segments;
* :mod:`.knots`: seed 000's knot placement (events, densification, l1 selection);
* :mod:`.config`, :mod:`.results`: settings and what a window solve returns;
* :mod:`.problem`, :mod:`.gauss_newton`: the window's least-squares problem and its solver,
  residual gate and covariance;
* :mod:`.knot_refinement`, :mod:`.observability`: knots beyond the first selection, and
  which station biases the data determine;
* :mod:`.estimator`: :func:`~.estimator.estimate`, one window end to end;
* :mod:`.windows`, :mod:`.stitcher`: sliding windows and their hand-over into one
  trajectory; :mod:`.residuals`, :mod:`.bias_files`: residual statistics, bias
  declarations and output tables.
"""

__all__: list[str] = []

"""Trajectory models with dynamics (seed 003).

* :mod:`.rocket`: gravity plus a thrust along the velocity with the rocket equation's
  magnitude, eight parameters, sensitivities by the variational equations;
  :mod:`.staging` adds a second stage at an unknown staging time;
* :mod:`.fit`: a model fitted to the raw measurements jointly with the biases
  (Levenberg-Marquardt), and its Cramér–Rao bound at the truth;
* :mod:`.start`, :mod:`.solve`: starting points (fixes, rough fixes from the rows, a
  range-hypothesis search for one station) and the one call the tools and the node make;
* :mod:`.thrust_spline`, :mod:`.adjoint_problem`, :mod:`.adjoint`: the seed's adjoint
  (4D-Var) assimilation of a free thrust profile;
* :mod:`.quadratic`: the seed's quadratic-polynomial baseline;
* :mod:`.observability`: what the data can and cannot determine, per parameter.
"""

__all__: list[str] = []

"""What the measurements of a dynamics fit can and cannot tell (seed 003, issue 15), after
the solve (:func:`classify`) and before it (:func:`classify_before`, at the start).

Per parameter, three figures: its posterior sigma (data and prior), the **bound** of the
data alone (the square root of the diagonal of the inverse information of the
measurements, infinite where that information is singular along a direction the
parameter takes part in) and its prior sigma. A bias is

* **estimated** when the data alone determine it to a tenth of its prior sigma or better,
* **weakly observable** up to three tenths,
* **not observable** beyond: the data hardly improve on the prior, and its estimate is
  the prior plus what the trajectory could not absorb.

The prior sigma is the declared plausible size of the bias (``bias_files``), which is why
the classes are stated against it. A flight parameter has no prior: it is estimated
unless its bound is infinite.

:func:`weakest_direction` says in words where a target's position is least known: the
largest axis of its position covariance at mid-flight, its angle to each station's line
of sight and the biases it trades against (correlation beyond 0.5).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.dynamics.adjoint import AdjointFit
from orbit_tracking.core.dynamics.fit import DynamicsFit, information_at
from orbit_tracking.core.dynamics.rocket import RocketModel
from orbit_tracking.core.estimation.results import BiasEstimate
from orbit_tracking.core.models.systematic import BiasParameter

__all__ = [
    'ESTIMATED',
    'NOT_OBSERVABLE',
    'WEAK',
    'ParameterObservability',
    'classify',
    'bias_estimates',
    'classify_before',
    'weakest_direction',
]

FloatArray = NDArray[np.float64]

ESTIMATED = 'estimated'
WEAK = 'weakly observable'
NOT_OBSERVABLE = 'not observable'

ESTIMATED_RATIO = 0.1
"""Largest bound / prior sigma of an estimated bias."""
WEAK_RATIO = 0.3
"""Largest bound / prior sigma of a weakly observable bias."""


@dataclass(frozen=True)
class ParameterObservability:
    """One parameter of a fit: ``name`` (``<target>/<parameter>`` or
    ``<station>/<bias>``), estimate, posterior sigma, the data-only bound, the prior sigma
    (inf without a prior) and the class."""

    name: str
    value: float
    sigma: float
    bound: float
    prior_sigma: float
    status: str

    def sentence(self) -> str:
        """One line for the summary and the log."""
        prior = f', prior {self.prior_sigma:.3g}' if math.isfinite(self.prior_sigma) else ''
        return (
            f'{self.name}: {self.status} (estimate {self.value:.6g}, sigma {self.sigma:.3g}, '
            f'bound of the data {self.bound:.3g}{prior})'
        )


def data_bounds(information: FloatArray) -> FloatArray:
    """Square roots of the diagonal of the inverse information (inf where singular)."""
    d = np.sqrt(np.maximum(np.diag(information), 1e-300))
    w, v = np.linalg.eigh(information / np.outer(d, d))
    small = w <= 1e-12 * max(float(w.max()), 1e-300)
    var = (v[:, ~small] ** 2 / w[~small]).sum(axis=1)
    var[np.any(np.abs(v[:, small]) > 1e-6, axis=1)] = math.inf
    return np.sqrt(var) / d


def _classes(
    names: Sequence[str],
    information: FloatArray,
    covariance: FloatArray,
    prior_sigma: FloatArray,
    values: FloatArray,
) -> list[ParameterObservability]:
    if not np.all(np.isfinite(information)):
        bound = np.full(len(names), math.inf)
    else:
        bound = data_bounds(information)
    sigma = np.sqrt(np.maximum(np.diag(covariance), 0.0))
    n_traj = len(names) - prior_sigma.size
    out = []
    for i, name in enumerate(names):
        prior = math.inf if i < n_traj else float(prior_sigma[i - n_traj])
        b = float(bound[i])
        if math.isinf(prior):
            status = ESTIMATED if math.isfinite(b) else NOT_OBSERVABLE
        elif b <= ESTIMATED_RATIO * prior:
            status = ESTIMATED
        elif b <= WEAK_RATIO * prior:
            status = WEAK
        else:
            status = NOT_OBSERVABLE
        out.append(
            ParameterObservability(name, float(values[i]), float(sigma[i]), b, prior, status)
        )
    return out


def classify(fit: DynamicsFit | AdjointFit) -> list[ParameterObservability]:
    """Every parameter of ``fit`` with its class (module docstring)."""
    values = np.concatenate(
        [
            *(fit.targets[t].theta for t in sorted(fit.targets)),
            fit.bias_values[[i for i, b in enumerate(fit.biases) if b.estimate]],
        ]
    )
    return _classes(fit.names, fit.information, fit.covariance, fit.prior_sigma, values)


def classify_before(
    obs: Observations,
    initial: Mapping[int, tuple[RocketModel, FloatArray]],
    biases: Sequence[BiasParameter],
) -> list[ParameterObservability]:
    """The classes the measurements promise *before* the solve: the information of the
    rocket model at the starting parameters (every row, the biases at their priors).
    ``value`` is the start and ``sigma`` the posterior sigma the fit would have if the
    start were the solution."""
    info, names, prior_sigma, values = information_at(obs, initial, biases)
    full = info + np.diag(
        np.concatenate([np.zeros(len(names) - prior_sigma.size), prior_sigma**-2.0])
    )
    d = np.sqrt(np.maximum(np.diag(full), 1e-300))
    cov = np.linalg.pinv(full / np.outer(d, d), rcond=1e-14, hermitian=True) / np.outer(d, d)
    return _classes(names, info, cov, prior_sigma, values)


def weakest_direction(fit: DynamicsFit | AdjointFit, obs: Observations, target_id: int) -> str:
    """The least-known direction of ``target_id``'s position at mid-flight, in words."""
    tf = fit.targets[target_id]
    tm = 0.5 * (tf.t0 + tf.t1)
    f = tf.model.propagate(tf.theta, [tm])
    assert f.sensitivity is not None
    gp = f.sensitivity[0, :3]  # (3, n) for the target's n parameters
    ids = sorted(fit.targets)
    lo = sum(len(fit.targets[t].theta) for t in ids[: ids.index(target_id)])
    sl = slice(lo, lo + len(tf.theta))
    pk = fit.covariance[sl, sl]
    if not np.all(np.isfinite(pk)):
        return f'target {target_id}: no covariance (the normal matrix is singular)'
    w, v = np.linalg.eigh(gp @ pk @ gp.T)
    u, sig = v[:, -1], math.sqrt(max(float(w[-1]), 0.0))
    pos = f.state[0, :3]
    parts = [
        f'target {target_id} at {tm:.1f} s: position least known along '
        f'({u[0]:+.2f}, {u[1]:+.2f}, {u[2]:+.2f}), sigma {sig:.3g} m '
        f'(next {math.sqrt(max(float(w[-2]), 0.0)):.3g} m)'
    ]
    angles = []
    for st in obs.stations:
        rows = np.flatnonzero(st.table.target_id == target_id)
        if rows.size == 0:
            continue
        i = rows[np.argmin(np.abs(st.table.time[rows] - tm))]
        los = pos - st.pose.position[i]
        cosang = abs(float(u @ los)) / float(np.linalg.norm(los))
        angles.append(
            f'{math.degrees(math.acos(min(cosang, 1.0))):.0f} deg from '
            f"{st.table.station_id}'s line of sight"
        )
    if angles:
        parts.append(', '.join(angles))
    n_traj = len(fit.names) - fit.prior_sigma.size
    if fit.prior_sigma.size and sig > 0.0:
        cross = u @ gp @ fit.covariance[sl, n_traj:]
        sb = np.sqrt(np.maximum(np.diag(fit.covariance)[n_traj:], 1e-300))
        corr = cross / (sig * sb)
        strong = [(fit.names[n_traj + j], float(c)) for j, c in enumerate(corr) if abs(c) > 0.5]
        if strong:
            parts.append('traded against ' + ', '.join(f'{n} (corr {c:+.2f})' for n, c in strong))
    return '; '.join(parts)


def bias_estimates(
    fit: DynamicsFit | AdjointFit, classes: Sequence[ParameterObservability]
) -> list[BiasEstimate]:
    """The fit's biases as :class:`~orbit_tracking.core.estimation.results.BiasEstimate`
    rows (``biases.csv``, ``trajectory/biases``): ``known`` when held at the declared value,
    else the class, with the bound and the prior sigma when it is not ``estimated``."""
    by_name = {p.name: p for p in classes}
    out = []
    for b, v in zip(fit.biases, fit.bias_values, strict=True):
        p = by_name.get(f'{b.station}/{b.name}')
        if p is None:  # held at its declared value
            out.append(
                BiasEstimate(b.station, b.name, float(v), b.sigma, b.prior, b.sigma, 'known')
            )
            continue
        status = p.status
        if status != ESTIMATED:
            status += (
                f': bound of the data {p.bound:.3g} against a prior sigma of {p.prior_sigma:.3g}'
            )
        out.append(BiasEstimate(b.station, b.name, float(v), p.sigma, b.prior, b.sigma, status))
    return out

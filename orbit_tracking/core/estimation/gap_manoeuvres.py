"""Manoeuvres an incomplete segment may hide, and the shape of those the knots follow only
approximately, carried in the published covariance.

Inside an incomplete segment one or two stations measure. A staging event or the onset
of a turn there changes the acceleration, and the window's spline (whose knots the few
measurements could support) cannot follow it; its formal covariance, conditional on the
spline being the true shape, then claims a metre where the error is tens of metres.

This module treats such manoeuvres as *consider parameters* (as range and orbit
determination software does with errors it cannot estimate): on a grid of instants
``tau_k`` inside every segment, a step ``a_k`` of the world acceleration (three axes),
each with prior variance ``q * width`` (``width`` the time it stands for): a white jerk
of density ``q`` [m^2/s^5] (``gap_manoeuvre_density``) restricted to the segments. The
estimate is left as it is (the steps are not solved for); its state covariance becomes
the posterior covariance of the model with the steps, their information from the data
included:

    true(t) = B(t) x + sum_k a_k (t - tau_k)_+^2 / 2,
    M = H_c^T H_c - U^T P U + C^-1,  U = J^T H_c,  L = P U,
    cov_state(t) += (B(t) L - B_c(t)) M^-1 (B(t) L - B_c(t))^T,

with ``J`` the whitened Jacobian of the window's parameters, ``P = (J^T J)^-1`` their
covariance, ``H_c`` the whitened measurement sensitivity to the steps and ``B_c(t)`` the
steps' own effect on the state. Where the measurements determine the acceleration (a
pulse radar, telemetry velocity) the data part of ``M`` is large and the term small;
where they do not, it grows with the prior, as it should. The posterior is centred on
the published estimate while the residuals show no sign of a step; a step the data see
but the knots leave unfitted (the knot test's business) is not covered by it.

The same term, with its own density, stands around every detected event (an acceleration
jump, a ramp's end). Knots of higher multiplicity there let the spline change its
acceleration or jerk, but only at the detected instant and in the spline's shape: a ramp end
placed 0.3 s early by noisy 1 Hz data leaves the velocity between samples off by tenths of
a metre per second where the formal covariance claims centimetres. Steps of the
acceleration on a grid across ``event +- half width`` stand for that unmodelled detail; the
data's information about them is taken into account as above (dense radar rows keep the
term small, sparse samples leave it large).

A third group of steps stands in the spans where the rough trajectory (the telemetry)
has no samples, a telemetry outage: no event can be detected there, so a turn's ramps or
a staging inside the outage get neither knots at their instants nor the term above, while
the stations still measure (the segment is complete). The spline with the base knots
rounds a 2-3 g turn's one-second ramp off; on the 35 aircraft draws of the robustness
families, with a GPS outage over the turn, the velocity next to the ramps was 0.5-1.6 m/s
off where its covariance claimed 0.02-0.1 m/s: most of the states beyond 5 sigma were
within a second of a true ramp end inside an outage. Its density is
``unseen_manoeuvre_density``, smaller than the incomplete segments' (the stations there
see the manoeuvre, and the data's information on the steps is counted as above).

A step moves every later row, so ``H_c`` is dense after its instant. But a row depends on
the steps before it through a quadratic in ``tau``: its part of ``H_c`` is ``Q V``, ``Q``
nine numbers per row and ``V`` the instants' powers. So ``H_c^T H_c`` and ``J^T H_c`` are
built from 9 x 9 and n x 9 sums over the rows after each instant, never from ``H_c``
itself: the cost grows with the rows plus the square of the instants, not their product.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from orbit_tracking.core.estimation.bspline import SplineTrajectory
from orbit_tracking.core.estimation.config import Segment
from orbit_tracking.core.estimation.coverage import merge_segments, unsampled_spans
from orbit_tracking.core.estimation.events import detector_reach

if TYPE_CHECKING:
    from orbit_tracking.core.data.observations import Observations
    from orbit_tracking.core.estimation.config import EstimatorConfig
    from orbit_tracking.core.estimation.problem import Problem

__all__ = [
    'GapManoeuvres',
    'event_spans',
    'gap_manoeuvres',
    'instants',
    'unseen_spans',
    'window_manoeuvres',
]

FloatArray = NDArray[np.float64]

MAX_INSTANTS = 240
"""Most step instants per target and group (incomplete segments, spans around events): the
grid is coarsened beyond this."""


@dataclass(frozen=True)
class GapManoeuvres:
    """The consider term of one target: step instants ``taus`` (k,) [s], the gain ``gain``
    (n_coef, 3k) of the spline coefficients to the steps (``P U``) and the steps'
    posterior covariance ``posterior`` (3k, 3k); column ``3 j + i`` is instant ``j``, world
    axis ``i``. ``density`` and ``event_density`` [m^2/s^5] are those of the incomplete
    segments' and the event spans' steps (0: that group is absent), ``event_spans`` the
    number of (merged) spans around events."""

    taus: FloatArray
    gain: FloatArray
    posterior: FloatArray
    density: float
    event_density: float = 0.0
    event_spans: int = 0
    unseen_density: float = 0.0
    unseen_spans: int = 0
    weak_densities: tuple[float, ...] = ()
    """The densities of the spans around weak changes, one each."""

    @property
    def note(self) -> str:
        """What the term stands for, for the window message."""
        parts = []
        if self.density > 0.0:
            parts.append(f'its incomplete segments may hide ({self.density:g} m^2/s^5)')
        if self.event_density > 0.0:
            parts.append(
                f'{self.event_spans} spans around events (found or doubtful) leave '
                f'unmodelled ({self.event_density:g} m^2/s^5)'
            )
        if self.unseen_density > 0.0:
            parts.append(
                f'{self.unseen_spans} spans where the rough trajectory had no samples may hide '
                f'({self.unseen_density:.3g} m^2/s^5)'
            )
        if self.weak_densities:
            parts.append(
                f'{len(self.weak_densities)} spans around weak changes leave unmodelled '
                f'({min(self.weak_densities):.3g}-{max(self.weak_densities):.3g} m^2/s^5)'
            )
        return ' and '.join(parts) + f' ({self.taus.size} acceleration steps)'

    def state_covariance(
        self,
        traj: SplineTrajectory,
        t: FloatArray,
        design: tuple[sp.csr_matrix, sp.csr_matrix] | None = None,
    ) -> FloatArray:
        """The term added to the state covariance (m, 6, 6) at times ``t``; ``design``:
        the position and velocity design matrices at ``t``, if already built."""
        m = t.shape[0]
        g = np.empty((m, 6, self.gain.shape[1]))
        for nu in (0, 1):
            dm = design[nu] if design is not None else traj.world_design(t, nu)
            bl = np.asarray(dm @ self.gain)  # (3m, 3k)
            g[:, 3 * nu : 3 * nu + 3] = bl.reshape(m, 3, -1)
        d = np.maximum(t[:, None] - self.taus[None, :], 0.0)  # (m, k)
        for i in range(3):
            g[:, i, i::3] -= 0.5 * d**2
            g[:, 3 + i, i::3] -= d
        gp = (g.reshape(6 * m, -1) @ self.posterior).reshape(m, 6, -1)
        out = np.matmul(gp, np.transpose(g, (0, 2, 1)))
        return 0.5 * (out + np.transpose(out, (0, 2, 1)))


def instants(segments: tuple[Segment, ...], step: float) -> tuple[FloatArray, FloatArray]:
    """The step instants: every ``step`` seconds across each segment, ends included,
    coarsened so that there are at most :data:`MAX_INSTANTS`; and the time each stands
    for [s] (a segment's instants share its length)."""
    length = sum(b - a for a, b in segments)
    if length <= 0.0:
        return np.zeros(0), np.zeros(0)
    step = max(step, length / (MAX_INSTANTS - 2 * len(segments)))
    taus, widths = [], []
    for a, b in segments:
        n = max(int(np.ceil((b - a) / step)), 1)
        w = np.full(n + 1, (b - a) / n)
        w[[0, -1]] *= 0.5
        taus.append(np.linspace(a, b, n + 1))
        widths.append(w)
    tau, width = np.concatenate(taus), np.concatenate(widths)
    order = np.argsort(tau, kind='stable')
    return tau[order], width[order]


def event_spans(
    events: tuple[float, ...], half_width: float, t0: float, t1: float
) -> tuple[Segment, ...]:
    """The spans ``event +- half_width`` inside [t0, t1], overlapping ones merged."""
    return tuple(
        merge_segments([(max(t0, e - half_width), min(t1, e + half_width)) for e in events])
    )


def gap_manoeuvres(
    rows: list[tuple[int, FloatArray, FloatArray, FloatArray, bool]],
    jac: sp.csr_matrix,
    cov: FloatArray,
    offset: int,
    n_coef: int,
    target: int,
    segments: tuple[Segment, ...],
    step: float,
    density: float,
    scale: float = 1.0,
    events: tuple[Segment, ...] = (),
    event_density: float = 0.0,
    unseen: tuple[Segment, ...] = (),
    unseen_density: float = 0.0,
    weak: tuple[tuple[Segment, float], ...] = (),
) -> GapManoeuvres | None:
    """The consider term of ``target``: acceleration steps every ``step`` seconds inside
    ``segments`` (:func:`instants`), each standing for its share of a white jerk of
    density ``density`` (prior variance ``density * width``), and likewise inside the
    spans ``events`` around detected events with density ``event_density`` and inside the
    ``unseen`` spans (where the rough trajectory had no samples) with ``unseen_density``,
    and each span of ``weak`` ``(span, density)`` (around weak changes) with its own.

    ``rows`` are the problem's per-row records (target, time, whitened d/d position and
    d/d velocity, telemetry flag) in the order of the rows of ``jac``; ``cov`` is
    ``(J^T J)^-1`` over all parameters and ``offset``, ``n_coef`` locate the target's
    coefficients in it. ``scale`` is the factor the window's covariance was scaled by for
    its misfit (the data are that much less informative). None when no group has both a
    span and a positive density.
    """
    groups = [
        (tuple((float(a), float(b)) for a, b in spans if b > a), q)
        for spans, q in (
            (segments, density),
            (events, event_density),
            (unseen, unseen_density),
            *(((span,), q) for span, q in weak),
        )
        if q > 0.0
    ]
    parts = [(*instants(spans, step), q) for spans, q in groups if spans]
    if not parts:
        return None
    taus = np.concatenate([p[0] for p in parts])
    variances = np.concatenate([p[2] * p[1] for p in parts])
    order = np.argsort(taus, kind='stable')
    taus, variances = taus[order], variances[order]
    k = taus.size
    t = np.concatenate([r[1] for r in rows])
    mine = np.concatenate([np.full(r[1].size, r[0] == target) for r in rows])
    fp = np.concatenate([r[2] for r in rows])
    fv = np.concatenate([r[3] for r in rows])
    if t.size != jac.shape[0]:
        raise ValueError('rows do not match the Jacobian')
    origin = float(taus[0])
    s = t - origin
    tau = taus - origin
    # a row after instant tau: fp (s - tau)^2 / 2 + fv (s - tau) = sum_p Q[:, 3 i + p] tau^p
    q = np.zeros((t.size, 9))
    for i in range(3):
        q[:, 3 * i] = fp[:, i] * 0.5 * s**2 + fv[:, i] * s
        q[:, 3 * i + 1] = -(fp[:, i] * s + fv[:, i])
        q[:, 3 * i + 2] = 0.5 * fp[:, i]
    v = np.zeros((9, 3 * k))
    for i in range(3):
        for p in range(3):
            v[3 * i + p, i::3] = tau**p
    # a row with n steps before it (n = 1..k) has H_c row Q_r V over their 3n columns;
    # H_c^T H_c between instants a and b and J^T H_c at instant a are sums over the rows
    # after max(a, b), resp. after a: sums taken from the last instant back
    n_before = np.searchsorted(tau, s, side='left')
    act = np.flatnonzero(mine & (n_before > 0))
    act = act[np.argsort(n_before[act], kind='stable')]
    bounds = np.searchsorted(n_before[act], np.arange(1, k + 2), side='left')
    hth = np.zeros((3 * k, 3 * k))
    u = np.zeros((jac.shape[1], 3 * k))
    tq = np.zeros((9, 9))
    wq = np.zeros((jac.shape[1], 9))
    for m in range(k - 1, -1, -1):
        these = act[bounds[m] : bounds[m + 1]]  # the rows with exactly m + 1 steps before
        if these.size:
            qm = q[these]
            tq += qm.T @ qm
            wq += np.asarray(jac[these].T @ qm)
        vm = v[:, 3 * m : 3 * m + 3]
        block = vm.T @ tq @ v[:, : 3 * m + 3]  # (3, 3m + 3)
        hth[3 * m : 3 * m + 3, : 3 * m + 3] = block
        hth[: 3 * m + 3, 3 * m : 3 * m + 3] = block.T
        u[:, 3 * m : 3 * m + 3] = wq @ vm
    pu = cov @ u
    info = (hth - u.T @ pu) / scale
    info = 0.5 * (info + info.T)
    info[np.diag_indices_from(info)] += 1.0 / np.repeat(variances, 3)
    posterior = np.linalg.inv(info)
    return GapManoeuvres(
        taus=taus.copy(),
        gain=pu[offset : offset + n_coef].copy(),
        posterior=0.5 * (posterior + posterior.T),
        density=density if segments and density > 0.0 else 0.0,
        event_density=event_density if events and event_density > 0.0 else 0.0,
        event_spans=len(events) if event_density > 0.0 else 0,
        unseen_density=unseen_density if unseen and unseen_density > 0.0 else 0.0,
        unseen_spans=len(unseen) if unseen_density > 0.0 else 0,
        weak_densities=tuple(q for _, q in weak if q > 0.0),
    )


def window_manoeuvres(
    prob: Problem,
    jac: sp.csr_matrix | None,
    cov: FloatArray,
    tid: int,
    segs: tuple[Segment, ...],
    events: tuple[float, ...],
    cfg: EstimatorConfig,
    scale: float,
    unseen: tuple[Segment, ...] = (),
    weak: tuple[tuple[float, float], ...] = (),
) -> GapManoeuvres | None:
    """The consider term of the manoeuvres target ``tid``'s incomplete segments and the
    ``unseen`` spans of its telemetry may hide and of the detail its ``events`` and
    ``weak`` changes ``(time, jerk jump)`` leave unmodelled (None when none applies)."""
    traj = prob.trajs[tid]
    spans = event_spans(events, cfg.event_manoeuvre_half_width, traj.t0, traj.t1)
    weak_spans = tuple(
        (span, cfg.weak_manoeuvre_gain * jump**2)
        for w, jump in weak
        for span in event_spans((w,), cfg.event_manoeuvre_half_width, traj.t0, traj.t1)
        if cfg.weak_manoeuvre_gain > 0.0 and jump > 0.0
    )
    if jac is None or not (
        (segs and cfg.gap_manoeuvre_density > 0.0)
        or (spans and cfg.event_manoeuvre_density > 0.0)
        or (unseen and cfg.unseen_manoeuvre_density > 0.0)
        or weak_spans
    ):
        return None
    return gap_manoeuvres(
        prob.rows,
        jac,
        cov,
        prob.offsets[tid],
        prob.trajs[tid].n_coef,
        tid,
        segs,
        cfg.gap_manoeuvre_step,
        cfg.gap_manoeuvre_density,
        scale,
        spans,
        cfg.event_manoeuvre_density,
        unseen,
        cfg.unseen_manoeuvre_density,
        weak_spans,
    )


def unseen_spans(
    obs: Observations, tid: int, t0: float, t1: float, cfg: EstimatorConfig
) -> tuple[Segment, ...]:
    """Where target ``tid``'s telemetry, the rough trajectory whose events make knots, has
    holes longer than two base knot spacings and three sampling intervals
    (:func:`~orbit_tracking.core.estimation.coverage.unsampled_spans`), widened by the
    event detector's reach (:func:`~orbit_tracking.core.estimation.events.detector_reach`):
    its fits take ``max(3, event_window / dt)`` samples on each side and see no event whose
    samples reach across a hole, three seconds at 1 Hz (the states just after an outage
    were off by 0.15 m/s at 0.02 m/s sigmas, robustness aircraft draw 9, 1-2 s after its
    outage's end, when the spans were widened by ``event_window`` alone)."""
    tel = obs.telemetry.get(tid) if cfg.use_telemetry else None
    if tel is None or len(tel) < 4:
        return ()
    t = np.sort(np.asarray(tel.time, dtype=np.float64))
    dt = float(np.median(np.diff(t)))
    hole = max(2.0 * cfg.knots.base_spacing, 3.0 * dt)
    reach = detector_reach(dt, cfg.knots.event_window)
    return tuple(unsampled_spans(t, t0, t1, hole, max(cfg.knots.event_window, reach)))

"""``diagnostic_msgs/DiagnosticArray`` helpers and the station-bias messages.

:func:`diagnostic_status` and :func:`diagnostic_array` build the diagnostics every node
publishes; :func:`biases_to_diagnostics` and :func:`diagnostics_to_biases` convert one
window's station biases to and from ``trajectory/biases`` (one status per station with
``<name>_bias`` and ``<name>_bias_sigma`` keys).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from orbit_tracking.core.models.systematic import ESTIMABLE_BIASES
from orbit_tracking.core.time import format_stamp
from orbit_tracking.ros.conversions.time import TimeBase

if TYPE_CHECKING:  # the estimator is heavy to import, and only the bias messages need it
    from orbit_tracking.core.estimation.results import BiasEstimate

__all__ = [
    'biases_to_diagnostics',
    'diagnostic_array',
    'diagnostic_status',
    'diagnostics_to_biases',
]


def diagnostic_status(
    name: str, level: int | bytes, message: str, values: dict[str, object], hardware_id: str = ''
) -> DiagnosticStatus:
    """A DiagnosticStatus with ``values`` as KeyValue strings (``level``: OK/WARN/ERROR)."""
    st = DiagnosticStatus()
    st.name = name
    st.level = level if isinstance(level, bytes) else bytes([level])
    st.message = message
    st.hardware_id = hardware_id
    st.values = [KeyValue(key=str(k), value=_fmt(v)) for k, v in values.items()]
    return st


def diagnostic_array(stamp: Time, statuses: Sequence[DiagnosticStatus]) -> DiagnosticArray:
    arr = DiagnosticArray()
    arr.header.stamp = stamp
    arr.status = list(statuses)
    return arr


_BIAS_SUFFIXES = ('bias', 'bias_sigma', 'bias_prior', 'bias_prior_sigma', 'bias_status')


def _bias_warns(status: str) -> bool:
    """An unobservable bias (held at its prior) or one that ended on a bound."""
    return status.startswith('unobservable') or ' bound' in status


def biases_to_diagnostics(
    biases: Sequence[BiasEstimate], t0: float, t1: float, timebase: TimeBase
) -> DiagnosticArray:
    """``trajectory/biases``: one window's station biases as a ``DiagnosticArray``.

    One ``DiagnosticStatus`` per station (in order of first appearance), ``name`` =
    ``hardware_id`` = station id, with the ``KeyValue``s ``<name>_bias``,
    ``<name>_bias_sigma``, ``<name>_bias_prior``, ``<name>_bias_prior_sigma`` (numbers
    written exactly, ``repr``) and ``<name>_bias_status`` per bias, then ``window_start``
    and ``window_end`` (stamps in decimal seconds). Level WARN when a bias of the station
    is unobservable (held at its prior) or ended on a bound, else OK.

    Parameters
    ----------
    biases : sequence of BiasEstimate
        An estimate's ``biases``.
    t0, t1 : float
        The window [TimeBase s]; ``header.stamp`` is the stamp of ``t1``.
    timebase : TimeBase
    """
    per_station: dict[str, list[BiasEstimate]] = {}
    for b in biases:
        per_station.setdefault(b.station, []).append(b)
    statuses = []
    window = {
        'window_start': format_stamp(timebase.ref_ns, t0),
        'window_end': format_stamp(timebase.ref_ns, t1),
    }
    for sid, bs in per_station.items():
        values: dict[str, object] = {}
        for b in bs:
            values[f'{b.name}_bias'] = repr(float(b.value))
            values[f'{b.name}_bias_sigma'] = repr(float(b.sigma))
            values[f'{b.name}_bias_prior'] = repr(float(b.prior))
            values[f'{b.name}_bias_prior_sigma'] = repr(float(b.prior_sigma))
            values[f'{b.name}_bias_status'] = b.status
        values.update(window)
        odd = [f'{b.name}: {b.status}' for b in bs if _bias_warns(b.status)]
        level = DiagnosticStatus.WARN if odd else DiagnosticStatus.OK
        message = '; '.join(odd) if odd else ', '.join(f'{b.name} {b.status}' for b in bs)
        statuses.append(diagnostic_status(sid, level, message, values, hardware_id=sid))
    return diagnostic_array(timebase.to_stamp(t1), statuses)


def diagnostics_to_biases(msg: DiagnosticArray) -> tuple[BiasEstimate, ...]:
    """The biases of a ``trajectory/biases`` message (inverse of
    :func:`biases_to_diagnostics`).

    The station is a status's ``hardware_id`` (its ``name`` if empty); a bias is every
    ``<name>_bias`` key of a known bias name. Missing ``_bias_prior`` /
    ``_bias_prior_sigma`` read as NaN, a missing ``_bias_status`` as ``''``; other keys
    are ignored.

    Raises
    ------
    ValueError
        A ``<name>_bias`` without its ``<name>_bias_sigma``, or a value that is not a
        number.
    """
    from orbit_tracking.core.estimation.results import BiasEstimate

    out = []
    for st in msg.status:
        sid = st.hardware_id or st.name
        kv = {k.key: k.value for k in st.values}
        for name in ESTIMABLE_BIASES:
            if f'{name}_bias' not in kv:
                continue
            if f'{name}_bias_sigma' not in kv:
                raise ValueError(f'station {sid}: {name}_bias without {name}_bias_sigma')
            try:
                value, sigma, prior, prior_sigma = (
                    float(kv.get(f'{name}_{suffix}', 'nan')) for suffix in _BIAS_SUFFIXES[:4]
                )
            except ValueError:
                raise ValueError(
                    f'station {sid}: {name} bias values must be numbers; got '
                    f'{[kv.get(f"{name}_{s}") for s in _BIAS_SUFFIXES[:4]]}'
                ) from None
            out.append(
                BiasEstimate(
                    sid, name, value, sigma, prior, prior_sigma, kv.get(f'{name}_bias_status', '')
                )
            )
    return tuple(out)


def _fmt(v: object) -> str:
    if isinstance(v, float):
        return f'{v:.9g}'
    return str(v)

"""Benchmark of the joint estimation of station systematic errors (``orbit-tracking bench
--suite biases``).

For each biased reference scenario and noise seed, the whole span is solved three ways:
biases **estimated** (declared with weak priors), **ignored** (not modelled) and **known**
(held at their true values). The tables give the trajectory errors against truth, every
estimated bias against its true value (``z`` = error / reported sigma), and for the
multi-target scenario the bias sigma of the joint solution next to each single-target one.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.errors import OrbitTrackingError
from orbit_tracking.core.estimation.bias_files import DEFAULT_PRIOR_SIGMA, auto_biases
from orbit_tracking.core.estimation.config import EstimatorConfig
from orbit_tracking.core.estimation.estimator import estimate
from orbit_tracking.core.estimation.results import Estimate
from orbit_tracking.core.metrics import nees
from orbit_tracking.core.models.systematic import BiasParameter
from orbit_tracking.core.sim.scenario import Scenario, load_scenario, truth_biases
from orbit_tracking.core.sim.simulator import SimulationResult, World, simulate
from orbit_tracking.core.sim.stream import feed_simulation
from orbit_tracking.core.triangulation.intersection import Gates
from orbit_tracking.core.triangulation.pipeline import TriangulationPipeline, fix_series

__all__ = ['BIAS_SCENARIOS', 'BiasBench', 'bench_biases', 'bias_tables', 'declare_biases']

BIAS_SCENARIOS: tuple[str, ...] = (
    'seed000_s1_bias',
    'seed000_s2_bias',
    'seed003_q3',
    'seed003_q4_multi',
)

EDGE_S = 2.0
"""Seconds trimmed at each end of the span for the trajectory figures: before the first
and after the last measurement the spline extrapolates (with an honest but huge sigma)."""

VARIANTS = ('estimated', 'ignored', 'known', 'estimated, thrust along v', 'known, thrust along v')

THRUST_SIGMA = 0.05
"""Sigma [m/s^2] of the thrust-along-velocity constraint in the variants that use it
(only for scenarios in an inertial frame, where the vehicles boost along the velocity)."""


def declare_biases(sc: Scenario, known: bool = False) -> tuple[BiasParameter, ...]:
    """The ``auto`` declaration for the scenario's stations (every measured field, and a
    satellite's rotation, with weak zero-mean priors); ``known`` holds each at the
    scenario's true value instead."""
    declared = auto_biases({st.id: st.fields for st in sc.stations})
    if not known:
        return declared
    truth = truth_biases(sc)
    return tuple(
        dataclasses.replace(b, prior=truth.get((b.station, b.name), 0.0), estimate=False)
        for b in declared
    )


@dataclass
class _Traj:
    pos: dict[str, list[float]] = field(default_factory=lambda: defaultdict(list))
    vel: dict[str, list[float]] = field(default_factory=lambda: defaultdict(list))
    nees: list[float] = field(default_factory=list)
    wall: list[float] = field(default_factory=list)
    failures: list[str] = field(default_factory=list)


@dataclass
class BiasBench:
    """Pooled figures of one scenario."""

    scenario: str
    gaps: tuple[tuple[float, float], ...]
    targets: tuple[int, ...]
    traj: dict[tuple[str, int], _Traj] = field(default_factory=dict)
    # (station, name) -> list of (value, sigma, truth, status)
    biases: dict[tuple[str, str], list[tuple[float, float, float, str]]] = field(
        default_factory=lambda: defaultdict(list)
    )
    # (station, name) -> {'joint' | target id: [sigma]}
    sigmas: dict[tuple[str, str], dict[str, list[float]]] = field(
        default_factory=lambda: defaultdict(lambda: defaultdict(list))
    )


def _observations(result: SimulationResult) -> Observations:
    # biased lines of sight do not intersect: the rough trajectory must not lose them
    pipe = TriangulationPipeline(gates=Gates(miss_probability=1.0))
    feed_simulation(pipe, result)
    return Observations.from_simulation(result, fix_series(pipe.flush()))


def _score(
    est: Estimate, result: SimulationResult, sc: Scenario, tid: int, pool: _Traj, gaps: Sequence
) -> None:
    tr = result.truth[tid]
    m = (tr.time >= sc.t_start + EDGE_S) & (tr.time <= sc.t_end - EDGE_S)
    t = tr.time[m]
    x, cov = est.targets[tid].states(t)
    e = x - np.hstack([tr.position[m], tr.velocity[m]])
    in_gap = np.zeros(t.size, dtype=bool)
    for a, b in gaps:
        in_gap |= (t >= a) & (t <= b)
    for key, sel in (('gap', in_gap), ('out', ~in_gap), ('all', np.ones_like(in_gap))):
        if np.any(sel):
            pool.pos[key].extend(np.linalg.norm(e[sel, :3], axis=1))
            pool.vel[key].extend(np.linalg.norm(e[sel, 3:], axis=1))
    stride = max(1, int(round(2.0 / max(float(np.median(np.diff(t))), 1e-3))))
    pool.nees.extend(nees(e[::stride, :3], cov[::stride, :3, :3]))


def bench_biases(
    scenarios: Sequence[str] = BIAS_SCENARIOS,
    seeds: int = 3,
    progress: bool = True,
    log: Callable[[str], None] = print,
) -> list[BiasBench]:
    """Every scenario, ``seeds`` noise seeds, the three bias treatments."""
    out = []
    for name in scenarios:
        base = load_scenario(name)
        bench = BiasBench(name, tuple(base.gaps), tuple(base.target_ids))
        for k in range(seeds):
            sc = dataclasses.replace(base, random_seed=base.random_seed + 1000 * k)
            result = simulate(sc, World(sc))
            obs = _observations(result)
            truth = truth_biases(sc)
            ids = list(sc.target_ids)
            for variant in VARIANTS:
                thrust = variant.endswith('thrust along v')
                if thrust and (sc.world_frame != 'eci' or len(ids) > 1):
                    continue  # boosters in an inertial frame; several targets need none
                biases = {
                    'estimated': declare_biases(sc),
                    'ignored': (),
                    'known': declare_biases(sc, known=True),
                }[variant.split(',')[0]]
                cfg = EstimatorConfig(
                    biases=biases, thrust_along_velocity=THRUST_SIGMA if thrust else 0.0
                )
                start = time.perf_counter()
                try:
                    est = estimate(obs, sc.t_start, sc.t_end, cfg, ids)
                except OrbitTrackingError as exc:
                    for tid in ids:
                        bench.traj.setdefault((variant, tid), _Traj()).failures.append(str(exc))
                    continue
                wall = time.perf_counter() - start
                for tid in ids:
                    pool = bench.traj.setdefault((variant, tid), _Traj())
                    pool.wall.append(wall)
                    if not est.success:
                        pool.failures.append(est.message)
                    _score(est, result, sc, tid, pool, sc.gaps)
                if variant == 'estimated':
                    for b in est.biases:
                        key = (b.station, b.name)
                        bench.biases[key].append((b.value, b.sigma, truth.get(key, 0.0), b.status))
                        if b.status == 'estimated':
                            bench.sigmas[key]['joint'].append(b.sigma)
            if len(ids) > 1:
                for tid in ids:
                    try:
                        single = estimate(
                            obs,
                            sc.t_start,
                            sc.t_end,
                            EstimatorConfig(biases=declare_biases(sc)),
                            [tid],
                        )
                    except OrbitTrackingError:
                        continue
                    for b in single.biases:
                        bench.sigmas[(b.station, b.name)][str(tid)].append(b.sigma)
            if progress:
                log(f'  {name} seed {k + 1}/{seeds} done')
        out.append(bench)
    return out


def _mean(x: Sequence[float]) -> float:
    return float(np.mean(x)) if len(x) else math.nan


def _rms(x: Sequence[float]) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else math.nan


def _g(x: float) -> str:
    return '—' if not math.isfinite(x) else f'{x:.3g}'


def bias_tables(benches: Sequence[BiasBench], seeds: int) -> str:
    """Markdown tables of :func:`bench_biases`."""
    lines = [
        f'Whole span solved once per seed ({seeds} seed(s)); trajectory figures exclude '
        f'{EDGE_S:g} s at each end. "estimated": the `auto` declaration, every measured '
        'field of every station a bias with a weak prior ('
        + ', '.join(f'{k} {v:g}' for k, v in DEFAULT_PRIOR_SIGMA.items() if k != 'clock')
        + '); "ignored": no bias modelled; '
        '"known": biases held at their true values; "thrust along v" (single-target '
        f'inertial-frame scenarios) adds the boost constraint with sigma {THRUST_SIGMA} '
        'm/s^2. The bias table is the "estimated" variant. NEES: mean over samples 2 s apart '
        '(3 is ideal).',
        '',
    ]
    for b in benches:
        lines += [f'### {b.scenario}', '']
        gap = bool(b.gaps)
        head = '| target | biases | '
        head += (
            'gap pos mean [m] | gap vel mean [m/s] | out pos RMS [m] | out vel RMS [m/s] |'
            if gap
            else 'pos RMS [m] | vel RMS [m/s] |'
        )
        head += ' pos NEES | wall [s] | not converged |'
        lines += [head, '|' + '---|' * (head.count('|') - 1)]
        for tid in b.targets:
            for variant in VARIANTS:
                p = b.traj.get((variant, tid))
                if p is None:
                    continue
                if gap:
                    figs = [
                        _mean(p.pos['gap']),
                        _mean(p.vel['gap']),
                        _rms(p.pos['out']),
                        _rms(p.vel['out']),
                    ]
                else:
                    figs = [_rms(p.pos['all']), _rms(p.vel['all'])]
                cells = [str(tid), variant, *(_g(f) for f in figs)]
                cells += [_g(_mean(p.nees)), _g(_mean(p.wall)), str(len(p.failures))]
                lines.append('| ' + ' | '.join(cells) + ' |')
        lines += [
            '',
            '| station | bias | truth | estimate (mean) | sigma (mean) | max abs z | status |',
            '|---|---|---|---|---|---|---|',
        ]
        for (sid, name), vals in sorted(b.biases.items()):
            truth = vals[0][2]
            z = [abs(v - t) / s for v, s, t, _ in vals if s > 0]
            statuses = sorted({st.split(':')[0] for *_, st in vals})
            lines.append(
                f'| {sid} | {name} | {_g(truth)} | {_g(_mean([v[0] for v in vals]))} | '
                f'{_g(_mean([v[1] for v in vals]))} | {_g(max(z) if z else math.nan)} | '
                f'{", ".join(statuses)} |'
            )
        if len(b.targets) > 1:
            cols = ['joint', *(str(t) for t in b.targets)]
            lines += [
                '',
                'Bias sigma, joint solution of all targets vs each target alone (mean over '
                'seeds; — = frozen as unobservable):',
                '',
                '| station | bias | '
                + ' | '.join('joint' if c == 'joint' else f'target {c} alone' for c in cols)
                + ' | joint smallest |',
                '|---|---|' + '---|' * (len(cols) + 1),
            ]
            for (sid, name), per in sorted(b.sigmas.items()):
                vals = [_mean(per.get(c, [])) for c in cols]
                singles = [v for v in vals[1:] if math.isfinite(v)]
                smallest = math.isfinite(vals[0]) and all(vals[0] < v for v in singles)
                lines.append(
                    f'| {sid} | {name} | '
                    + ' | '.join(_g(v) for v in vals)
                    + f' | {"yes" if smallest else "no"} |'
                )
        lines.append('')
    return '\n'.join(lines)

"""The randomised seed-003 family in the benchmark (``orbit-tracking bench --suite seed003
--draws N``, issue 15): both dynamics models on scenarios drawn apart from the reference
ones (:mod:`orbit_tracking.core.sim.seed003_family`: one to three satellites, a second
stage in a third of the draws, biases in half), each against the Cramér–Rao bound of its
own draw.

Every draw is solved as a user without the truth would: biases declared (``auto``) where
the draw has them, the number of stages found by the fit (``stages: auto``). The rocket
model's bound is that of the true flight (with its second stage where it has one); the
adjoint's is that of the spline closest to the true thrust (:func:`~orbit_tracking.core.
dynamics.adjoint.adjoint_bound`), with a jump at a true staging (where the fit has one
only if the rocket fit found the staging). The
table gives, per model and kind of draw, the median / 95th percentile / worst of the
ratio of the RMS error to the bound, the mean NEES and how many draws were a success.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial

import numpy as np
from scipy import stats

from orbit_tracking.core.dynamics.adjoint import AdjointConfig, adjoint_bound
from orbit_tracking.core.dynamics.fit import bound_at
from orbit_tracking.core.dynamics.solve import RocketConfig, fit_model
from orbit_tracking.core.dynamics.staging import StagedRocketModel
from orbit_tracking.core.errors import OrbitTrackingError
from orbit_tracking.core.sim.scenario import scenario_from_dict, truth_biases
from orbit_tracking.core.sim.seed003_family import seed003_draw
from orbit_tracking.core.sim.simulator import simulate
from orbit_tracking.tools.bench.biases import declare_biases
from orbit_tracking.tools.bench.seed003 import (
    Seed003Row,
    observations_of,
    score_states,
    truth_flight_models,
)

__all__ = ['FAMILY_MODELS', 'FamilyDraw', 'bench_seed003_family', 'family_table']

FAMILY_MODELS: tuple[str, ...] = ('rocket', 'adjoint')


@dataclass
class FamilyDraw:
    """One draw of the randomised seed-003 family with one model."""

    seed: int
    model: str
    satellites: int
    biases: int
    stages: int
    success: bool
    pos_ratio: float
    vel_ratio: float
    nees: float
    wall: float
    message: str = ''


def _failed(seed: int, model: str, sats: int, nb: int, stages: int, msg: str) -> FamilyDraw:
    nan = math.nan
    return FamilyDraw(seed, model, sats, nb, stages, False, nan, nan, nan, nan, msg)


def bench_seed003_family(
    draws: int | Sequence[int],
    progress: bool = True,
    log: Callable[[str], None] = print,
    models: Sequence[str] = FAMILY_MODELS,
) -> list[FamilyDraw]:
    """Each model on scenarios of :func:`~orbit_tracking.core.sim.seed003_family.
    seed003_draw` (seeds 0 ... draws - 1, or the seeds given), against each draw's bound."""
    seeds = range(draws) if isinstance(draws, int) else draws
    out = []
    for done, seed in enumerate(seeds, 1):
        sc = scenario_from_dict(seed003_draw(seed), f'seed003_family[{seed}]')
        result = simulate(sc)
        obs = observations_of(result)
        declared = declare_biases(sc) if truth_biases(sc) else ()
        cfg = RocketConfig(gm=sc.gm, stages=0)
        truth = truth_flight_models(sc, cfg)
        stages = 2 if sc.targets[0]['second_stage'] is not None else 1
        sats = len(obs.stations)
        for model in models:
            start = time.perf_counter()
            try:
                fit = fit_model(obs, model, biases=declared, config=cfg)
            except OrbitTrackingError as exc:
                out.append(_failed(seed, model, sats, len(declared), stages, str(exc)))
                continue
            wall = time.perf_counter() - start
            if model == 'adjoint':
                thrust = {
                    tid: (m.epoch, th[:6], partial(m.thrust, th)) for tid, (m, th) in truth.items()
                }
                jumps = {  # the bound with the spline the fit would use: jumps at stagings
                    tid: (float(th[8]),)
                    for tid, (m, th) in truth.items()
                    if isinstance(m, StagedRocketModel)
                }
                bound = adjoint_bound(obs, thrust, declared, AdjointConfig(gm=sc.gm), jumps)[0]
            else:
                bound = bound_at(obs, truth, declared)[0]
            row = Seed003Row(sc.name, '', model, 0)
            score_states(row, result, 0, fit.targets[0].states, bound)
            out.append(
                FamilyDraw(
                    seed,
                    model,
                    sats,
                    len(declared),
                    stages,
                    fit.success,
                    math.sqrt(np.mean(row.pos) / np.mean(row.crb_pos)),
                    math.sqrt(np.mean(row.vel) / np.mean(row.crb_vel)),
                    float(np.mean(row.nees)),
                    wall,
                    '' if fit.success else fit.message,
                )
            )
        if progress and done % 10 == 0:
            log(f'  seed003 family: {done}/{len(seeds)} draws')
    return out


def _kinds(draws: Sequence[FamilyDraw]) -> list[tuple[str, list[FamilyDraw]]]:
    return [
        ('all', list(draws)),
        ('one satellite', [d for d in draws if d.satellites == 1]),
        ('two or three satellites', [d for d in draws if d.satellites > 1]),
        ('second stage', [d for d in draws if d.stages == 2]),
        ('biases declared', [d for d in draws if d.biases > 0]),
    ]


def family_table(draws: Sequence[FamilyDraw]) -> str:
    """Per model and kind of draw: median / 95th percentile / worst of the ratios to each
    draw's bound, the NEES, and the draws that were not a success."""
    lo, hi = (float(x) for x in stats.chi2.ppf([0.025, 0.975], 6))

    def q(vals: list[float]) -> str:
        if not vals:
            return '— / — / —'
        a = np.asarray(vals)
        return f'{np.median(a):.2f} / {np.percentile(a, 95):.2f} / {a.max():.2f}'

    n_draws = len({d.seed for d in draws})
    lines = [
        f'Randomised seed-003 family (`orbit_tracking/core/sim/seed003_family.py`, drawn '
        f'apart from the reference scenarios): {n_draws} draws, solved with biases declared '
        'where the draw has them and the number of stages found by the fit. Ratios are RMS '
        "error over the root mean trace of the draw's own Cramér–Rao bound (median / 95th "
        "percentile / worst); the NEES is each draw's mean 6-dof state NEES every 2 s, "
        f'"in band" when inside the chi-square(6) 95 % interval [{lo:.2f}, {hi:.2f}] (its '
        'samples along one flight are correlated, so this is the band of one sample). '
        'Ratios and NEES are over the successes; a draw that is not a success is counted '
        'and listed, never scored.\n',
        '| model | draws | n | success | pos ratio | vel ratio | mean NEES (median / 95th / '
        'worst) | NEES in band | wall [s] (median / worst) |',
        '|---|---|---|---|---|---|---|---|---|',
    ]
    models = [m for m in FAMILY_MODELS if any(d.model == m for d in draws)]
    for model in models:
        for kind, sel in _kinds([d for d in draws if d.model == model]):
            if not sel:
                continue
            ok = [d for d in sel if d.success and math.isfinite(d.pos_ratio)]
            in_band = sum(lo <= d.nees <= hi for d in ok)
            wall = (
                f'{np.median([d.wall for d in ok]):.2f} / {max(d.wall for d in ok):.2f}'
                if ok
                else '—'
            )
            lines.append(
                f'| {model} | {kind} | {len(sel)} | {len(ok)} | '
                f'{q([d.pos_ratio for d in ok])} | {q([d.vel_ratio for d in ok])} | '
                f'{q([d.nees for d in ok])} | {in_band}/{len(ok)} | {wall} |'
            )
    failed = [d for d in draws if not d.success]
    if failed:
        lines.append('')
        for d in failed:
            lines.append(
                f'- draw {d.seed}, {d.model} ({d.satellites} satellite(s), {d.stages} '
                f'stage(s), {d.biases} biases): not a success ({d.message}).'
            )
    return '\n'.join(lines)

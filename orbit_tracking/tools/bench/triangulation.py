"""The benchmark: accuracy against truth and the Cramér–Rao bound, and wall time.

``orbit-tracking bench`` runs every method on the reference scenarios over several noise
seeds and prints Markdown tables; ``--write-docs`` puts them into ``docs/BENCHMARKS.md``
between markers, so the figures in the docs always come from this command.

Triangulation methods compared:

* ``weighted`` (ours): lines weighted by their angle covariance and distance, N stations,
  radar points, gates on;
* ``seed003-midpoint``: seed 003's method as published — equal weights (for two lines
  the midpoint of the common perpendicular), no gates;
* ``seed003-lowpass``: the same after the seed's low-pass filter (ε = 0.95);
* ``weighted+lowpass``: ours after the same filter.
"""

from __future__ import annotations

import dataclasses
import math
import re
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from orbit_tracking.core.errors import GeometryError
from orbit_tracking.core.metrics import nees
from orbit_tracking.core.sim.scenario import Scenario, load_scenario
from orbit_tracking.core.sim.simulator import SimulationResult, World, simulate
from orbit_tracking.core.sim.stream import feed_simulation
from orbit_tracking.core.triangulation.alignment import AlignConfig, Aligner, EpochLines
from orbit_tracking.core.triangulation.intersection import (
    Gates,
    cramer_rao_bound,
    intersect,
    triangulate,
)

__all__ = [
    'TRIANGULATION_SCENARIOS',
    'TriangulationRow',
    'bench_triangulation',
    'markdown_table',
    'write_docs',
]

TRIANGULATION_SCENARIOS = ('seed003_q2', 'seed003_q3', 'seed000_s1', 'seed000_s2', 'seed004_sea')
METHODS = ('weighted', 'weighted+lowpass', 'seed003-midpoint', 'seed003-lowpass')


@dataclass
class TriangulationRow:
    """Pooled figures of one method on one scenario over all seeds (outside gaps)."""

    scenario: str
    method: str
    fixes: int
    epochs: int
    rms_m: float
    median_m: float
    crb_m: float
    nees: float
    wall_ms_per_fix: float

    @property
    def efficiency(self) -> float:
        """RMS error over the RMS Cramér–Rao bound (1 is the best possible)."""
        return self.rms_m / self.crb_m if self.crb_m > 0 else math.nan


def _epochs(result: SimulationResult, config: AlignConfig) -> list[EpochLines]:
    al = Aligner(config)
    feed_simulation(al, result)
    return al.flush()


def _midpoint_fix(ep: EpochLines) -> np.ndarray | None:
    lines = ep.lines
    if len(lines) < 2 and not any(ln.has_range for ln in lines):
        return None
    origins = np.stack([ln.point() if ln.has_range else ln.origin for ln in lines])
    infos = np.stack(
        [
            np.eye(3) if ln.has_range else np.eye(3) - np.outer(ln.direction, ln.direction)
            for ln in lines
        ]
    )
    try:
        return intersect(origins, infos)[0]
    except GeometryError:
        return None


def _run(method: str, result: SimulationResult, world: World) -> tuple[list, float, int]:
    """(rows of (time, target, position, covariance or None, crb, truth), wall seconds,
    epochs with at least one line)."""
    eps = 0.95 if method.endswith('lowpass') else None
    t0 = time.perf_counter()
    epochs = _epochs(result, AlignConfig(smoothing_eps=eps))
    out = []
    for ep in epochs:
        if method.startswith('weighted'):
            res = triangulate(ep.lines, Gates())
            if res.success and res.fix is not None:
                out.append((ep, res.fix.position, res.fix.covariance))
        else:
            x = _midpoint_fix(ep)
            if x is not None:
                out.append((ep, x, None))
    wall = time.perf_counter() - t0
    rows = []
    for ep, x, cov in out:
        truth = world.targets[ep.target_id].state(ep.time)[0, :3]
        rows.append((ep.time, ep.target_id, x, cov, cramer_rao_bound(ep.lines, truth), truth))
    return rows, wall, sum(1 for ep in epochs if ep.lines)


def bench_triangulation(
    scenarios: Sequence[str] = TRIANGULATION_SCENARIOS, seeds: int = 3, progress: bool = True
) -> list[TriangulationRow]:
    """Run every triangulation method on every scenario for ``seeds`` noise seeds."""
    table = []
    for name in scenarios:
        base = load_scenario(name)
        pooled: dict[str, dict[str, list]] = {
            m: {'err': [], 'crb': [], 'nees': [], 'wall': [], 'n': [], 'epochs': []}
            for m in METHODS
        }
        for k in range(seeds):
            sc: Scenario = dataclasses.replace(base, random_seed=base.random_seed + 1000 * k)
            world = World(sc)
            result = simulate(sc, world)
            for method in METHODS:
                rows, wall, n_epochs = _run(method, result, world)
                p = pooled[method]
                p['wall'].append(wall)
                p['epochs'].append(n_epochs)
                p['n'].append(len(rows))
                for t, _tid, x, cov, crb, truth in rows:
                    if any(a <= t <= b for a, b in sc.gaps):
                        continue
                    e = x - truth
                    p['err'].append(float(np.linalg.norm(e)))
                    p['crb'].append(float(np.trace(crb)))
                    if cov is not None:
                        p['nees'].append(float(nees(e[None], cov[None])[0]))
            if progress:
                print(f'  {name} seed {k + 1}/{seeds} done', flush=True)
        for method in METHODS:
            p = pooled[method]
            err = np.array(p['err'])
            n = int(sum(p['n']))
            table.append(
                TriangulationRow(
                    scenario=name,
                    method=method,
                    fixes=n // seeds,
                    epochs=int(sum(p['epochs'])) // seeds,
                    rms_m=float(np.sqrt(np.mean(err**2))) if err.size else math.nan,
                    median_m=float(np.median(err)) if err.size else math.nan,
                    crb_m=float(np.sqrt(np.mean(p['crb']))) if p['crb'] else math.nan,
                    nees=float(np.mean(p['nees'])) if p['nees'] else math.nan,
                    wall_ms_per_fix=1e3 * sum(p['wall']) / max(int(sum(p['epochs'])), 1),
                )
            )
    return table


def markdown_table(rows: Sequence[TriangulationRow], seeds: int) -> str:
    lines = [
        'Triangulation fixes against truth, outside incomplete segments, pooled over '
        f'{seeds} noise '
        'seed(s). CRB: root mean trace of the single-epoch Cramér–Rao bound of the same lines at '
        'the truth; efficiency = RMS error / CRB (1 is optimal); NEES: mean normalised error '
        'squared of the reported covariance (3 if honest); fixes/epochs: fixes passing the gates '
        'per run, of the epochs with lines; time: core pipeline per epoch.',
        '',
        '| scenario | method | fixes/epochs | RMS 3-D error [m] | median [m] | CRB [m] | '
        'efficiency | mean NEES | time [ms/epoch] |',
        '|---|---|---|---|---|---|---|---|---|',
    ]

    def num(x: float, fmt: str) -> str:
        return format(x, fmt) if math.isfinite(x) else '—'

    for r in rows:
        nees_txt = f'{r.nees:.2f}' if math.isfinite(r.nees) else 'n/a'
        lines.append(
            f'| {r.scenario} | {r.method} | {r.fixes}/{r.epochs} | {num(r.rms_m, ".3f")} | '
            f'{num(r.median_m, ".3f")} | {num(r.crb_m, ".3f")} | {num(r.efficiency, ".3f")} | '
            f'{nees_txt} | {r.wall_ms_per_fix:.2f} |'
        )
    return '\n'.join(lines)


_BEGIN = (
    '<!-- BEGIN bench:{name} (generated by orbit-tracking bench --write-docs; do not edit) -->'
)
_END = '<!-- END bench:{name} -->'


def write_docs(path: str | Path, name: str, text: str) -> None:
    """Replace the generated section ``name`` of a Markdown file (appended if absent)."""
    path = Path(path)
    doc = path.read_text() if path.exists() else '# Benchmarks\n'
    begin, end = _BEGIN.format(name=name), _END.format(name=name)
    block = f'{begin}\n{text}\n{end}'
    pattern = re.compile(re.escape(begin) + r'.*?' + re.escape(end), re.S)
    doc = (
        pattern.sub(lambda _m: block, doc)
        if pattern.search(doc)
        else doc.rstrip() + '\n\n' + block + '\n'
    )
    path.write_text(doc)

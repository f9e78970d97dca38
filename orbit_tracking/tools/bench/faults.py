"""The fault-injection suite over real DDS (``orbit-tracking bench --suite faults``,
``test/test_faults.py``): every class of :mod:`~orbit_tracking.tools.bench.fault_catalogue`
thrown at the running ``triangulation``, ``estimator`` and ``results`` nodes during a replay
of a regression bag (:func:`~orbit_tracking.tools.bench.fault_replay.replay_with_faults`).

:func:`run_faults` runs the clean replay and one replay per group of classes, ``lanes`` of
them at a time (each in its own DDS domain: a replay spends most of its time waiting for
the nodes' once-a-second ``/diagnostics``, so two share two cores well), and decides each
class:

* a node that died, hung or logged a traceback during the class's phase is the class's
  doing; the group's other classes go on in a new replay;
* a trajectory that differs from the clean replay, or a problem after the last phase (a
  node that hung at the end of the stream, a traceback, an unclean exit), is attributed by
  re-running each class of the group alone;
* a class is *counted* by a node when a rejection counter of that node grew during its
  phase; a count that comes later (a residual gate at the window solve, a stream held until
  the next messages show it off the time line) and is not in the clean replay is credited
  to the class when it is the only one of its replay that the node did not count at once,
  or the only such one of its stop and the count grew after that stop; else the class is
  re-run alone. So is a class that no count of its group replay can be given to: its count
  may have come during another class's phase (a window held until the next real window
  drops it) and been taken for that class's.

A class passes when no node dies, hangs or logs a traceback, each of its ``targets``
counts it, and the trajectory equals the clean replay's (the same states, positions within
:data:`POSITION_TOLERANCE_M`). :func:`faults_table` prints the results as Markdown;
:data:`EXTRA_ROWS` is where more rows (the node restart) join the table.

The nodes of every replay run one copy of the source tree, taken when the suite starts: a
file edited meanwhile would otherwise make the replays compare different code.
"""

from __future__ import annotations

import math
import os
import queue
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from orbit_tracking.tools.bench.fault_catalogue import (
    CATALOGUE,
    CONTROL,
    GROUPS,
    NODES,
    FaultClass,
)
from orbit_tracking.tools.bench.fault_replay import (
    DEFAULT_BAG,
    Phase,
    ReplayRun,
    load_bag,
    replay_with_faults,
)

__all__ = [
    'EXTRA_ROWS',
    'POSITION_TOLERANCE_M',
    'FaultResult',
    'FaultSuite',
    'faults_table',
    'run_faults',
    'select_faults',
]

POSITION_TOLERANCE_M = 1e-6
"""Largest position difference from the clean replay that is the same trajectory."""


@dataclass(frozen=True)
class FaultResult:
    """What became of one fault class.

    Attributes
    ----------
    fault : FaultClass
    sent : int
        Bad messages published.
    counted : mapping of node to tuple of str
        The rejection counters credited to the class, per target node (empty: none).
    counted_how : str
        ``at once`` (in its phase) or ``by the end`` (the end of its replay).
    crash : str
        A node that died, hung or logged a traceback ('' if none).
    states, clean_states : int
        ``trajectory/states`` of its replay and of the clean one (-1: its replay ended
        early).
    max_dp_m : float
        Largest position difference from the clean replay at the stamps both have (NaN:
        no trajectory).
    symptoms : str
        Symptom counters that grew (resets, data dropped after one, failed windows, ...).
    run : str
        The replay that decided it: its group's, or ``alone``.
    restart_loss : str
        States lost to a node restart (the restart row; '—' for the fault classes).
    missing_states, extra_states : int
        States of the clean replay this one lacks; states it has that the clean replay has
        not (other stamps or targets, or repeats).
    logs : str
        Folder of the node logs of the replay that decided it ('' if not kept).
    max_dp_sigma, sigma_tolerance : float
        For a row whose windows are solved anew (the restart row), the largest difference
        of a state component from the clean replay in units of the row's own published
        sigma, and the bound it must stay within instead of :data:`POSITION_TOLERANCE_M`
        (NaN: the row is held to the 1e-6 m rule of the fault classes).
    """

    fault: FaultClass
    sent: int
    counted: Mapping[str, tuple[str, ...]]
    counted_how: str
    crash: str
    states: int
    clean_states: int
    max_dp_m: float
    symptoms: str = ''
    run: str = ''
    restart_loss: str = '—'
    missing_states: int = 0
    extra_states: int = 0
    logs: str = ''
    max_dp_sigma: float = math.nan
    sigma_tolerance: float = math.nan

    @property
    def problems(self) -> list[str]:
        """Why the class fails (empty: it passes)."""
        out = [self.crash] if self.crash else []
        missing = [n for n in self.fault.targets if not self.counted.get(n)]
        if missing:
            out.append(f'no rejection counted by {" and ".join(missing)}')
        if self.states < 0:
            if not self.crash:
                out.append('its replay did not finish')
        elif self.missing_states or self.extra_states or not self._close():
            out.append(
                f'trajectory differs from the clean replay: {self.states} states (clean '
                f'{self.clean_states}; {self.missing_states} missing, {self.extra_states} '
                f'extra), largest position difference {self.max_dp_m:.3g} m'
            )
        return out

    def _close(self) -> bool:
        if math.isnan(self.sigma_tolerance):
            return self.max_dp_m <= POSITION_TOLERANCE_M
        return self.max_dp_sigma <= self.sigma_tolerance

    @property
    def passed(self) -> bool:
        return not self.problems


EXTRA_ROWS: list[Callable[[], FaultResult]] = []
"""More rows for :func:`faults_table`, each made after the catalogue has run. The hook for
the node-restart row: append a function that kills and restarts a node during a replay and
returns ``FaultResult(FaultClass('estimator_restart', 'restart', 'estimator killed and
started again', (), (), lambda ref: []), ..., restart_loss='<states lost>')``."""


@dataclass(frozen=True)
class FaultSuite:
    """:func:`run_faults`'s outcome: a result per class (catalogue order), the clean
    replay, the number of replays and the wall time."""

    results: tuple[FaultResult, ...]
    clean: ReplayRun
    replays: int
    wall_s: float


# -- deciding a replay ---------------------------------------------------------------------


def _compare(run: ReplayRun, clean: ReplayRun) -> tuple[int, float, int, int]:
    """States of a replay, the largest position difference from the clean replay at the
    stamps both have, and the clean states it lacks and the states it has in excess."""
    if run.aborted or not run.final:
        return -1, math.nan, 0, 0
    common = set(run.states) & set(clean.states)
    diffs = (float(np.max(np.abs(run.states[k] - clean.states[k]))) for k in common)
    missing = len(set(clean.states) - common)
    extra = run.state_msgs - len(common)  # other stamps or targets, and repeats
    return run.state_msgs, max(diffs, default=0.0), missing, extra


def _symptoms(phase: Phase | None, run: ReplayRun, clean: ReplayRun, alone: bool) -> str:
    grown: Counter[str] = Counter()
    if phase is not None:
        for n, d in phase.symptoms.items():
            grown.update({f'{n} {k}': v for k, v in d.items()})
    if alone:  # what grew after the phase is the class's too
        for n, d in run.final_symptoms.items():
            base = clean.final_symptoms.get(n, {})
            for k, v in d.items():
                extra = v - base.get(k, 0) - grown.get(f'{n} {k}', 0)
                if extra > 0:
                    grown[f'{n} {k}'] += extra
    return ', '.join(f'{k} +{v}' for k, v in sorted(grown.items()))


def _late_counts(run: ReplayRun, clean: ReplayRun, node: str) -> dict[str, int]:
    """Rejection counters of ``node`` that ended higher than in the clean replay by more
    than the phases account for."""
    grown: Counter[str] = Counter()
    for ph in run.phases.values():
        grown.update(ph.grew.get(node, {}))
    base = clean.final.get(node, {})
    out = {}
    for k, v in run.final.get(node, {}).items():
        extra = v - base.get(k, 0) - grown.get(k, 0)
        if extra > 0:
            out[k] = extra
    return out


def _decide(
    group: Sequence[FaultClass], run: ReplayRun, clean: ReplayRun
) -> tuple[list[FaultResult], list[list[FaultClass]], str]:
    """The results a replay decides, the replays still needed, and a line saying why."""
    alone = len(group) == 1
    where = 'alone' if alone else f'group {group[0].group} ({len(group)} classes)'
    if run.aborted:
        name, why = run.aborted
        f = next(x for x in group if x.name == name)
        ph = run.phases.get(name)
        counted = {n: tuple(sorted(ph.grew.get(n, {}))) for n in f.targets} if ph else {}
        result = FaultResult(
            f,
            ph.sent if ph else 0,
            counted,
            'at once',
            why,
            -1,
            clean.state_msgs,
            math.nan,
            _symptoms(ph, run, clean, False),
            where,
            logs=str(run.log_dir or ''),
        )
        rest = [x for x in group if x.name != name]
        return [result], [rest] if rest else [], f'{name}: {why}'
    n_states, dp, missing, extra = _compare(run, clean)
    same = not missing and not extra and dp <= POSITION_TOLERANCE_M
    if not alone and (not same or run.end_problem):
        why = 'its trajectory differs' if not same else run.end_problem.splitlines()[0][:160]
        return [], [[f] for f in group], f'{where}: {why}; its classes again one by one'
    credit: dict[str, dict[str, tuple[str, ...]]] = {}
    again: list[FaultClass] = []
    for node in NODES:
        uncounted = [f for f in group if node in f.targets and not run.phases[f.name].grew[node]]
        if not uncounted:
            continue
        late = _late_counts(run, clean, node)
        if alone:
            if late:
                credit.setdefault(uncounted[0].name, {})[node] = tuple(sorted(late))
            continue
        for k, seg in enumerate(run.segments if late else ()):
            these = [f for f in uncounted if f.name in seg.faults]
            # the only class of the replay not counted at once: what grew from its stop on;
            # else the only one of its stop: what grew until the next stop
            later = run.segments[k:] if len(uncounted) == 1 else [seg]
            keys = sorted({key for s in later for key in s.grew.get(node, {}) if key in late})
            if keys and len(these) == 1:
                credit.setdefault(these[0].name, {})[node] = tuple(keys)
        again += [f for f in uncounted if node not in credit.get(f.name, {}) and f not in again]
    results = []
    for f in group:
        if f in again:
            continue
        ph = run.phases[f.name]
        counted = {n: tuple(sorted(ph.grew.get(n, {}))) for n in f.targets}
        counted.update(credit.get(f.name, {}))
        crash = ''
        if ph.tracebacks:
            crash = 'traceback in ' + ', '.join(sorted(ph.tracebacks))
        elif alone and run.end_problem:
            crash = run.end_problem[:3000]  # with the end of the node's log
        results.append(
            FaultResult(
                f,
                ph.sent,
                counted,
                'by the end' if f.name in credit else 'at once',
                crash,
                n_states,
                clean.state_msgs,
                dp,
                _symptoms(ph, run, clean, alone),
                where,
                missing_states=missing,
                extra_states=extra,
                logs=str(run.log_dir or ''),
            )
        )
    why = f'{where}: decided {len(results)}'
    if again:
        why += f'; counts that came late for {[f.name for f in again]}: again one by one'
    return results, [[f] for f in again], why


# -- the suite -------------------------------------------------------------------------------


def _domains(lanes: int) -> list[int]:
    """DDS domains of the lanes: the run's (``ROS_DOMAIN_ID``, else ``1 + pid % 100``),
    then the same moved by 100 (test runs pick theirs among 1-100)."""
    base = int(os.environ.get('ROS_DOMAIN_ID') or 1 + os.getpid() % 100)
    other = base + 100 if base + 100 <= 232 else base - 100
    return [base, other][: max(1, min(lanes, 2))]


def _snapshot(dest: Path) -> Path | None:
    """A copy of the source tree's ``orbit_tracking`` and ``config`` for the nodes of every
    replay: one suite tests one version of the code, whatever is edited while it runs.
    None when the nodes come from an install space (which a build replaces at once)."""
    import shutil

    from orbit_tracking.tools.live import package_location

    where = package_location()
    if where.bin_dir is not None or where.source_root is None:
        return None
    skip = shutil.ignore_patterns('__pycache__', '*.pyc')
    for name in ('orbit_tracking', 'config'):
        shutil.copytree(where.source_root / name, dest / name, ignore=skip)
    return dest


def run_faults(
    faults: Sequence[FaultClass] = CATALOGUE,
    log_dir: Path | None = None,
    bag: Path = DEFAULT_BAG,
    rate: float = 10.0,
    lanes: int = 2,
    budget_s: float = 1800.0,
    progress: Callable[[str], None] | None = None,
) -> FaultSuite:
    """Run the clean replay and every class of ``faults`` (one replay per
    :attr:`FaultClass.group`, then what attribution needs; see the module docstring).

    Classes whose replay would start after ``budget_s`` wall seconds are reported as not
    run. Node logs go to ``log_dir`` (default a temporary folder, removed), one folder per
    replay. The nodes of every replay run a copy of the source tree taken at the start.

    Raises
    ------
    RuntimeError
        The clean replay fails, or the nodes of a replay do not come up.
    """
    import tempfile

    say = progress or (lambda _text: None)
    loaded = load_bag(Path(bag))
    t0 = time.monotonic()
    free: queue.Queue[int] = queue.Queue()
    for d in _domains(lanes):
        free.put(d)
    counter = iter(range(1, 10_000))
    lock = threading.Lock()

    with tempfile.TemporaryDirectory(prefix='orbit_tracking_faults_') as tmp:
        root = Path(log_dir or tmp)
        source = _snapshot(Path(tmp) / 'source')

        def replay(group: Sequence[FaultClass]) -> ReplayRun:
            with lock:
                k = next(counter)
            label = 'clean' if not group else group[0].name if len(group) == 1 else group[0].group
            domain = free.get()
            try:
                return replay_with_faults(
                    group, root / f'{k:02d}_{label}', loaded, rate, domain, source
                )
            finally:
                free.put(domain)

        groups = [[f for f in faults if f.group == g] for g in GROUPS]
        jobs: deque[list[FaultClass]] = deque(g for g in groups if g)
        jobs += [[f] for f in faults if f.group not in GROUPS]
        done: dict[str, FaultResult] = {}
        clean: ReplayRun | None = None
        parked: list[tuple[list[FaultClass], ReplayRun]] = []
        replays = 0
        with ThreadPoolExecutor(max_workers=len(_domains(lanes))) as pool:
            running: dict[Future[ReplayRun], list[FaultClass]] = {pool.submit(replay, []): []}
            while running or jobs:
                while jobs and len(running) < len(_domains(lanes)):
                    group = jobs.popleft()
                    if time.monotonic() - t0 > budget_s:
                        for f in group:
                            done[f.name] = _not_run(f)
                        continue
                    running[pool.submit(replay, group)] = group
                if not running:
                    break
                finished, _ = wait(running, return_when=FIRST_COMPLETED)
                for fut in finished:
                    group = running.pop(fut)
                    run = fut.result()
                    replays += 1
                    label = ', '.join(f.name for f in group[:3]) + (
                        '...' if len(group) > 3 else ''
                    )
                    say(
                        f'replay {replays} [{label or "clean"}]: {run.state_msgs} states in '
                        f'{run.wall_s:.0f} s'
                        + (f'; {run.aborted[0]}: {run.aborted[1]}' if run.aborted else '')
                        + (f'; {run.end_problem.splitlines()[0][:160]}' if run.end_problem else '')
                    )
                    if not group:
                        clean = run
                        if run.aborted or run.end_problem or not run.states:
                            raise RuntimeError(
                                'bench faults: the clean replay failed '
                                f'({run.end_problem or "no states"}); logs in {run.log_dir}'
                            )
                        todo, parked = parked, []
                    else:
                        todo = [(group, run)]
                    if clean is None:
                        parked += todo
                        continue
                    for g, r in todo:
                        results, more, why = _decide(g, r, clean)
                        say('  ' + why)
                        done.update((x.fault.name, x) for x in results)
                        jobs.extendleft(reversed(more))
        assert clean is not None
    say(f'{replays} replays in {time.monotonic() - t0:.0f} s')
    return FaultSuite(
        tuple(done[f.name] for f in faults if f.name in done),
        clean,
        replays,
        time.monotonic() - t0,
    )


def _not_run(f: FaultClass) -> FaultResult:
    return FaultResult(f, 0, {}, '', 'not run (time budget spent)', -1, -1, math.nan, run='none')


def select_faults(names: Sequence[str] | None) -> list[FaultClass]:
    """The classes named, or every class of a group named (``control``: the
    :data:`~orbit_tracking.tools.bench.fault_catalogue.CONTROL` class); the whole catalogue
    and the control for none.

    Raises
    ------
    ValueError
        A name that is neither a class nor a group.
    """
    every = (*CATALOGUE, CONTROL)
    if not names:
        return list(every)
    known = {f.name for f in every} | {f.group for f in every}
    bad = [n for n in names if n not in known]
    if bad:
        raise ValueError(f'unknown fault class(es) or group(s) {bad}; see fault_catalogue.py')
    return [f for f in every if f.name in names or f.group in names]


# -- the table -------------------------------------------------------------------------------


def faults_table(suite: FaultSuite, command: str) -> str:
    """Markdown table of a :func:`run_faults` outcome (and :data:`EXTRA_ROWS`), with its
    caption, a summary line and the machine it ran on."""
    import platform

    from rclpy.utilities import get_rmw_implementation_identifier

    rows = [r for r in suite.results if r.fault is not CONTROL]
    rows += [make() for make in EXTRA_ROWS]
    control = [r for r in suite.results if r.fault is CONTROL]

    def counted(r: FaultResult) -> str:
        parts = []
        for n in r.fault.targets:
            keys = r.counted.get(n, ())
            parts.append(f'{n}: ' + (', '.join(f'`{k}`' for k in keys) if keys else '**none**'))
        return '; '.join(parts) + (' (by the end)' if r.counted_how == 'by the end' else '')

    def trajectory(r: FaultResult) -> str:
        if r.states < 0:
            return '—'
        text = f'{r.states} / {r.max_dp_m:.2g}'
        if not math.isnan(r.sigma_tolerance):
            text += f' ({r.max_dp_sigma:.2g} σ, at most {r.sigma_tolerance:g} σ)'
        if r.missing_states or r.extra_states:
            text += f' ({r.missing_states} missing, {r.extra_states} extra)'
        return text

    lines = [
        f'Fault injection over real DDS: `{DEFAULT_BAG.name}` replayed at 10x through the '
        '`triangulation`, `estimator` and `results` nodes (each its own process), the bad '
        'messages published by a second participant at stops of the replay. sent: bad '
        "messages; counted: the rejection counters that grew in each target node's "
        '`/diagnostics`; crash: a node that died, hung or logged a traceback; trajectory: '
        '`trajectory/states` messages / largest position difference [m] from the clean '
        f'replay ({suite.clean.state_msgs} states) at the stamps both have, and the states '
        'missing or in excess; restart loss: states lost to a node '
        'restart (its own row); symptoms: resets, dropped data, failed windows. A class '
        'passes when no node crashes, every target counts it and the trajectory is the clean '
        f'one (positions within {POSITION_TOLERANCE_M:g} m). The restart row solves its '
        'windows anew after the restart, so it passes when no state is lost or repeated and '
        "every state is within the tolerance shown of the clean one, in the row's own "
        'published sigma.',
        '',
        '| fault class | in issue table | sent | counted | crash | trajectory '
        '| restart loss | symptoms | verdict |',
        '|---|---|---|---|---|---|---|---|---|',
    ]
    for r in rows:
        crash = r.crash.splitlines()[0][:100] if r.crash else ''
        lines.append(
            f'| `{r.fault.name}`: {r.fault.what} | {"yes" if r.fault.table else ""} | {r.sent} '
            f'| {counted(r)} | {crash} | {trajectory(r)} | {r.restart_loss} | {r.symptoms} '
            f'| {"pass" if r.passed else "**FAIL**"} |'
        )
    failed = [r.fault.name for r in rows if not r.passed]
    lines += [
        '',
        f'{len(rows) - len(failed)} of {len(rows)} classes pass'
        + (f'; failing: {", ".join(failed)}.' if failed else '.'),
    ]
    for r in control:
        seen = not r.crash and not any(r.counted.values()) and r.max_dp_m > POSITION_TOLERANCE_M
        lines += [
            '',
            f'Control (`{r.fault.name}`: {r.fault.what}): trajectory {trajectory(r)}, counted '
            f'by {counted(r)}: the suite '
            + (
                'sees a message the nodes use.'
                if seen
                else '**does not see it: its checks are void**.'
            ),
        ]
    lines += [
        '',
        f'Measured by `{command}` on {platform.machine()} ({platform.python_implementation()} '
        f'{platform.python_version()}, {os.cpu_count()} cores, '
        f'{get_rmw_implementation_identifier()}) in {suite.wall_s:.0f} s '
        f'({suite.replays} replays).',
    ]
    return '\n'.join(lines)

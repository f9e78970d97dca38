"""Issue 14's silent-failure target on a reference scenario: seed004_sea (an aircraft over
sea, 2-3 g turns, one inside a GPS outage) solved end to end with the default settings has
no state beyond 5 sigma while its windows claim success."""

from __future__ import annotations

import numpy as np

from orbit_tracking.core.estimation.windows import solve_windows, stitch
from orbit_tracking.core.sim.scenario import load_scenario
from orbit_tracking.core.sim.simulator import World, simulate
from orbit_tracking.tools.bench.estimator import fixes_for
from orbit_tracking.tools.estimator_parameters import estimator_configs


def test_seed004_sea_has_no_silent_state() -> None:
    """Measured at the scenario's own seed, states every 0.1 s: 29 windows, all successful,
    no state beyond 5 sigma, mean position NEES 1.95. Before the weak changes' consider
    term (gentle turn ramps below the event thresholds), 29 velocity states at 441-444 s
    were beyond 5 sigma; before the consider terms of issue 14, a 2.5 g turn in the GPS
    outage left 130-830 m errors at 0.2 m sigmas."""
    sc = load_scenario('seed004_sea')
    result = simulate(sc, World(sc))
    est, win, _ = estimator_configs({})
    ests = solve_windows(fixes_for(result), est, win)
    assert ests and all(e.success for e in ests), [e.message[:200] for e in ests if not e.success]
    tid = sc.target_ids[0]
    tr = result.truth[tid]
    step = max(1, int(round(0.1 / float(np.median(np.diff(tr.time))))))
    tt, x, cov = stitch(ests, tr.time[::step], tid)
    assert tt.size > 0.9 * tr.time[::step].size  # the pass is covered
    i = np.searchsorted(tr.time, tt)
    e = x - np.hstack([tr.position[i], tr.velocity[i]])
    d2_pos = np.einsum('ki,kij,kj->k', e[:, :3], np.linalg.inv(cov[:, :3, :3]), e[:, :3])
    d2_vel = np.einsum('ki,kij,kj->k', e[:, 3:], np.linalg.inv(cov[:, 3:, 3:]), e[:, 3:])
    silent = tt[(d2_pos > 25.0) | (d2_vel > 25.0)]
    assert silent.size == 0, np.round(silent[:20], 1)
    assert 1.0 < float(np.mean(d2_pos)) < 4.0

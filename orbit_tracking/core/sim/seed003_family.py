"""A randomised family of seed-003 scenarios (issue 15), drawn separately from the
reference ones: boosting vehicles seen by two or three satellites, for stating the dynamics
models' accuracy on geometries and vehicles we did not choose.

Each draw (:func:`seed003_draw`, seeded):

* **vehicle** (inertial ``eci`` frame, 120 s observed from 50 s): a start 20-80 km above a
  random point of the Earth, 700-1600 m/s at 25-65 deg above the local horizon toward a
  random azimuth; thrust along the velocity with exhaust speed 2500-4200 m/s and mass time
  130-260 s at the start;
* **a second stage** in a third of the draws: a staging 20-100 s after the start to an
  exhaust speed of 2500-4500 m/s, its mass time 40-130 s longer than what is left of the
  flight;
* **one, two or three satellites** (a quarter, 40 %, 35 % of the draws) on two-body
  orbits 1500-4500 km above the Earth, 10-45 deg of arc from the vehicle's start, moving in
  a random direction (circular speed times 0.98-1.02); the Earth hides the vehicle from a
  satellite when it is in the way;
* **noise** 2e-6 to 1.5e-5 per satellite, 5 Hz, unsynchronised;
* **systematic errors** in half of the draws: each satellite's (d_alpha, d_beta, d_theta)
  normal with sigma 3e-4.

A draw where a satellite sees the vehicle less than half the time is redrawn (the next
sub-seed); the dict is a scenario file's content (:func:`~.scenario.scenario_from_dict`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from orbit_tracking.core import frames

__all__ = ['seed003_draw']

GM = 3.986005e14
T0, SPAN = 50.0, 120.0


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _perpendicular(rng: np.random.Generator, u: np.ndarray) -> np.ndarray:
    w = _unit(rng.normal(size=3))
    return _unit(w - (w @ u) * u)


def _rotate_toward(u: np.ndarray, w: np.ndarray, angle: float) -> np.ndarray:
    """``u`` turned by ``angle`` [rad] toward the perpendicular unit vector ``w``."""
    return math.cos(angle) * u + math.sin(angle) * w


def _sees_enough(pos: np.ndarray, vel: np.ndarray, target: np.ndarray) -> bool:
    """Whether a satellite (straight-line motion is enough over 2 min for this check)
    sees ``target`` (three samples) without the Earth in the way."""
    for k, dt in enumerate((0.0, 60.0, 120.0)):
        p = pos + vel * dt
        d = target[k] - p
        rng_ = float(np.linalg.norm(d))
        u = d / rng_
        s = min(max(-float(p @ u), 0.0), rng_)
        if np.linalg.norm(p + s * u) <= frames.WGS84_B:
            return False
    return True


def seed003_draw(seed: int) -> dict[str, Any]:
    """One scenario of the family (module docstring) as a scenario dict."""
    for attempt in range(50):
        rng = np.random.default_rng([seed, attempt])
        up = _unit(rng.normal(size=3))
        east = _perpendicular(rng, up)
        r0 = up * (frames.WGS84_A + rng.uniform(20e3, 80e3))
        climb = math.radians(rng.uniform(25.0, 65.0))
        speed = rng.uniform(700.0, 1600.0)
        v0 = speed * (math.cos(climb) * east + math.sin(climb) * up)
        c = rng.uniform(2500.0, 4200.0)
        tau = rng.uniform(130.0, 260.0)
        # rough positions at the start, middle and end (straight line, for visibility only)
        mean_acc = c / (tau - SPAN / 2)
        target = np.array(
            [r0 + _unit(v0) * (speed * t + 0.5 * mean_acc * t * t) for t in (0.0, 60.0, 120.0)]
        )
        n_sat = int(rng.choice([1, 2, 3], p=[0.25, 0.4, 0.35]))
        stations = []
        ok = True
        for k in range(n_sat):
            w = _perpendicular(rng, up)
            direction = _rotate_toward(up, w, math.radians(rng.uniform(10.0, 45.0)))
            radius = frames.WGS84_A + rng.uniform(1500e3, 4500e3)
            pos = direction * radius
            vel = _perpendicular(rng, direction) * math.sqrt(GM / radius) * rng.uniform(0.98, 1.02)
            # where the satellite is at t = 50 s; its state is given at t = 0
            pos0, vel0 = pos - vel * T0, vel
            if not _sees_enough(pos, vel, target):
                ok = False
                break
            sigma = float(rng.uniform(2e-6, 1.5e-5))
            station: dict[str, Any] = {
                'id': f'sat{k + 1:02d}',
                'kind': 'satellite',
                'platform': {
                    'type': 'orbit',
                    't0': 0.0,
                    'position': pos0.tolist(),
                    'velocity': vel0.tolist(),
                },
                'rate_hz': 5.0,
                'first_epoch': T0 + float(rng.uniform(0.0, 0.2)),
                'sigma': {'los_alpha': sigma, 'los_beta': sigma},
            }
            stations.append(station)
        if not ok:
            continue
        second = None
        if rng.uniform() < 1.0 / 3.0:
            t_s = T0 + float(rng.uniform(20.0, 100.0))
            second = {
                'time_s': t_s,
                'exhaust_speed_m_s': float(rng.uniform(2500.0, 4500.0)),
                'tau0_s': T0 + SPAN + float(rng.uniform(40.0, 130.0)),
            }
        biased = bool(rng.integers(0, 2))
        if biased:
            for st in stations:
                st['bias'] = {
                    name: float(rng.normal(0.0, 3e-4))
                    for name in ('los_alpha', 'los_beta', 'los_theta')
                }
        return {
            'name': f'seed003_family_{seed}',
            'description': 'A randomised seed-003 draw (orbit_tracking.core.sim.seed003_family).',
            'world_frame': 'eci',
            'epoch': 1700000000.0,
            'span': [T0, T0 + SPAN],
            'random_seed': int(seed) * 7919 + attempt,
            'gm': GM,
            'truth_rate_hz': 5.0,
            'targets': [
                {
                    'id': 0,
                    'model': 'boost',
                    't0': T0,
                    'position': r0.tolist(),
                    'velocity': v0.tolist(),
                    'exhaust_speed_m_s': float(c),
                    'tau0_s': float(T0 + tau),
                    'second_stage': second,
                }
            ],
            'stations': stations,
        }
    raise RuntimeError(f'no visible geometry for family seed {seed} in 50 attempts')

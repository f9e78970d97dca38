"""The YAML schema of scenario files (``config/scenarios/<name>.yaml``).

:data:`SCENARIO_SCHEMA` validates one scenario mapping after inheritance is resolved, fills
in defaults and raises :class:`~orbit_tracking.core.errors.ConfigError` on the first wrong
key or value (see :mod:`orbit_tracking.core.schema`). Its parts (geodetic positions, flight
tracks, orbit states, targets, platforms, ships, stations, telemetry) are private to this
module. Units are in the key names (``_m``, ``_m_s``, ``_deg``, ``_s``, ``_hz``); see
``docs/SCENARIOS.md`` for every key.
"""

from __future__ import annotations

import re

from orbit_tracking.core import frames
from orbit_tracking.core.models.measurements import FIELDS, KIND_FIELDS
from orbit_tracking.core.models.systematic import BIAS_PARAMETERS
from orbit_tracking.core.schema import (
    REQUIRED,
    Bool,
    Choice,
    Intervals,
    ListOf,
    Nullable,
    Num,
    Obj,
    Str,
    Tagged,
    Vec,
)
from orbit_tracking.core.sim.telemetry import ERROR_MODELS

__all__ = ['SCENARIO_SCHEMA']

_ID = re.compile(r'^[A-Za-z][A-Za-z0-9_]*$')
_ID_CHECK = Str(lambda s: bool(_ID.match(s)), 'an identifier (letter, then letters/digits/_)')

_GEODETIC = {
    'latitude_deg': (Num(ge=-90.0, le=90.0), REQUIRED),
    'longitude_deg': (Num(ge=-180.0, le=360.0), REQUIRED),
    'height_m': (Num(ge=-1000.0, le=1.0e6), 0.0),
}
_LEG = Obj(
    {
        'duration_s': (Num(gt=0.0), REQUIRED),
        'load_factor': (Num(ge=1.0, le=12.0), 1.0),
        'turn': (Choice(('none', 'left', 'right')), 'none'),
        'speed_rate_m_s2': (Num(ge=-50.0, le=50.0), 0.0),
        'path_angle_rate_deg_s': (Num(ge=-20.0, le=20.0), 0.0),
    }
)
_TRACK = {
    'start': (Obj(_GEODETIC), REQUIRED),
    'speed_m_s': (Num(gt=0.0, le=5000.0), REQUIRED),
    'heading_deg': (Num(ge=-360.0, le=360.0), REQUIRED),
    'start_time': (Num(), None),
    'transition_s': (Num(gt=0.0), 2.0),
    'legs': (ListOf(_LEG, min_len=1), REQUIRED),
}
_ORBIT_STATE = {
    't0': (Num(), 0.0),
    'position': (Nullable(Vec(3)), None),
    'velocity': (Nullable(Vec(3)), None),
    'elements': (
        Nullable(
            Obj(
                {
                    'semi_major_axis_m': (Num(gt=6.0e6), REQUIRED),
                    'eccentricity': (Num(ge=0.0, lt=1.0), REQUIRED),
                    'inclination_deg': (Num(ge=0.0, le=180.0), REQUIRED),
                    'raan_deg': (Num(ge=-360.0, le=360.0), REQUIRED),
                    'argument_of_perigee_deg': (Num(ge=-360.0, le=360.0), REQUIRED),
                    'true_anomaly_deg': (Num(ge=-360.0, le=360.0), REQUIRED),
                }
            )
        ),
        None,
    ),
    'j2': (Bool(), False),
}
_TARGETS = Tagged(
    'model',
    {
        'boost': Obj(
            {
                'id': (Num(integer=True, ge=0), REQUIRED),
                't0': (Num(), REQUIRED),
                'position': (Vec(3), REQUIRED),
                'velocity': (Vec(3), REQUIRED),
                'exhaust_speed_m_s': (Num(gt=0.0), REQUIRED),
                'tau0_s': (Num(), REQUIRED),
                'j2': (Bool(), False),
                'second_stage': (
                    Nullable(
                        Obj(
                            {
                                'time_s': (Num(), REQUIRED),
                                'exhaust_speed_m_s': (Num(gt=0.0), REQUIRED),
                                'tau0_s': (Num(), REQUIRED),
                            }
                        )
                    ),
                    None,
                ),
            }
        ),
        'orbit': Obj({'id': (Num(integer=True, ge=0), REQUIRED), **_ORBIT_STATE}),
        'powered_ascent': Obj(
            {
                'id': (Num(integer=True, ge=0), REQUIRED),
                'liftoff_time': (Num(), REQUIRED),
                'stages': (
                    ListOf(
                        Obj(
                            {
                                'mass_kg': (Num(gt=0.0), REQUIRED),
                                'propellant_kg': (Num(gt=0.0), REQUIRED),
                                'mass_flow_kg_s': (Num(gt=0.0), REQUIRED),
                                'exhaust_speed_m_s': (Num(gt=0.0), REQUIRED),
                                'coast_before_s': (Num(ge=0.0), 0.0),
                            }
                        ),
                        min_len=1,
                    ),
                    REQUIRED,
                ),
                'pitch_program_deg': (ListOf(Vec(2), min_len=1), REQUIRED),
                'cd_area_m2': (Num(ge=0.0), 0.0),
            }
        ),
        'aircraft': Obj({'id': (Num(integer=True, ge=0), REQUIRED), **_TRACK}),
    },
)
_PLATFORM = Tagged(
    'type',
    {
        'fixed': Obj(_GEODETIC),
        'orbit': Obj(_ORBIT_STATE),
        'ship': Obj(
            {
                'ship': (_ID_CHECK, REQUIRED),
                'lever_arm_m': (Vec(3), [0.0, 0.0, 0.0]),
            }
        ),
    },
)
_SHIP = Obj(
    {
        'id': (_ID_CHECK, REQUIRED),
        **_TRACK,
        'attitude': (
            Obj(
                {
                    'roll_amplitude_deg': (Num(ge=0.0, le=45.0), 0.0),
                    'roll_period_s': (Num(gt=0.0), 10.0),
                    'pitch_amplitude_deg': (Num(ge=0.0, le=20.0), 0.0),
                    'pitch_period_s': (Num(gt=0.0), 10.0),
                    'yaw_amplitude_deg': (Num(ge=0.0, le=20.0), 0.0),
                    'yaw_period_s': (Num(gt=0.0), 15.0),
                }
            ),
            {},
        ),
    }
)
_FIELD_NUMS = Obj({f: (Num(gt=0.0), None) for f in FIELDS})
_STATION = Obj(
    {
        'id': (_ID_CHECK, REQUIRED),
        'kind': (Choice(tuple(KIND_FIELDS)), REQUIRED),
        'platform': (_PLATFORM, REQUIRED),
        'fields': (Nullable(ListOf(Choice(FIELDS), min_len=1)), None),
        'rate_hz': (Num(gt=0.0, le=1000.0), REQUIRED),
        'first_epoch': (Nullable(Num()), None),
        'sigma': (_FIELD_NUMS, REQUIRED),
        'bias': (Obj({p: (Num(), None) for p in BIAS_PARAMETERS}), {}),
        'clock_bias_s': (Num(ge=-1.0, le=1.0), 0.0),
        'elevation_mask_deg': (Nullable(Num(ge=-90.0, le=90.0)), None),
        'max_range_m': (Nullable(Num(gt=0.0)), None),
        'earth_occlusion': (Bool(), True),
        'dropouts': (Intervals({'fields': (Nullable(ListOf(Choice(FIELDS), 1)), None)}), []),
        'loss_probability': (Num(ge=0.0, lt=1.0), 0.0),
        'gross_errors': (
            Obj(
                {
                    'count': (Num(integer=True, ge=0, le=100000), 0),
                    'min_sigma': (Num(gt=0.0, le=1.0e6), 20.0),
                    'max_sigma': (Num(gt=0.0, le=1.0e6), 1000.0),
                }
            ),
            {'count': 0, 'min_sigma': 20.0, 'max_sigma': 1000.0},
        ),
        'targets': (Nullable(ListOf(Num(integer=True, ge=0), min_len=1)), None),
    }
)
_TELEMETRY = Obj(
    {
        'kind': (Choice(('drift', 'gps')), 'drift'),
        'error_model': (Choice(ERROR_MODELS), 'drift'),
        'rate_hz': (Num(gt=0.0, le=1000.0), REQUIRED),
        'first_epoch': (Nullable(Num()), None),
        'targets': (Nullable(ListOf(Num(integer=True, ge=0), min_len=1)), None),
        'position_sigma_m': (Num(gt=0.0), REQUIRED),
        'velocity_sigma_m_s': (Num(gt=0.0), REQUIRED),
        'position_drift_m': (Num(ge=0.0), 0.0),
        'velocity_drift_m_s': (Num(ge=0.0), 0.0),
        # parameters of the other error models (core/sim/telemetry.py, docs/SCENARIOS.md)
        'position_walk_m_sqrt_s': (Num(ge=0.0, le=100.0), 0.0),
        'position_markov_m': (Num(ge=0.0, le=1.0e4), 0.0),
        'position_markov_tau_s': (Num(gt=0.0, le=1.0e5), 100.0),
        'velocity_markov_m_s': (Num(ge=0.0, le=100.0), 0.0),
        'velocity_markov_tau_s': (Num(gt=0.0, le=1.0e5), 100.0),
        'position_bias_m': (Num(ge=0.0, le=1.0e4), 0.0),
        'position_drift_rate_m_s': (Num(ge=0.0, le=100.0), 0.0),
        'velocity_bias_m_s': (Num(ge=0.0, le=100.0), 0.0),
        'position_delay_s': (Num(ge=-1.0, le=1.0), 0.0),
        'velocity_delay_s': (Num(ge=-1.0, le=1.0), 0.0),
        'jump_rate_hz': (Num(ge=0.0, le=1.0), 0.0),
        'jump_sigma_m': (Num(ge=0.0, le=1.0e4), 0.0),
        'position_quantum_m': (Num(ge=0.0, le=1.0e3), 0.0),
        'velocity_quantum_m_s': (Num(ge=0.0, le=100.0), 0.0),
        'outages': (Intervals(), []),
    }
)
SCENARIO_SCHEMA = Obj(
    {
        'name': (_ID_CHECK, REQUIRED),
        'description': (Str(), ''),
        'world_frame': (Choice(('earth', 'eci')), REQUIRED),
        'epoch': (Num(gt=0.0), 1.7e9),
        'span': (Vec(2), REQUIRED),
        'random_seed': (Num(integer=True, ge=0), 0),
        'gm': (Num(gt=0.0), frames.WGS84_GM),
        'launch': (
            Nullable(Obj({**_GEODETIC, 'azimuth_deg': (Num(ge=-360.0, le=360.0), REQUIRED)})),
            None,
        ),
        'truth_rate_hz': (Num(gt=0.0, le=1000.0), 20.0),
        'evaluation': (
            Obj(
                {
                    'gaps': (Intervals(), []),
                    'output_step_s': (Num(gt=0.0), 1.0),
                }
            ),
            {},
        ),
        'targets': (ListOf(_TARGETS, min_len=1), REQUIRED),
        'platforms': (ListOf(_SHIP), []),
        'stations': (ListOf(_STATION, min_len=1), REQUIRED),
        'telemetry': (Nullable(_TELEMETRY), None),
    }
)
"""Schema of a whole scenario file: ``name``, ``world_frame``, ``epoch`` [s], ``span`` [s],
``targets``, ``platforms``, ``stations``, ``telemetry`` and the other top-level keys."""

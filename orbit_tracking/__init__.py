"""orbit_tracking: trajectory estimation of flight vehicles from many tracking sensors.

The numerical libraries run single-threaded unless the environment says otherwise
(``OPENBLAS_NUM_THREADS``, ``OMP_NUM_THREADS``, ``MKL_NUM_THREADS``, set here before numpy
loads when they are unset). The matrices of a window are small: threads that spin up for
each product cost more than they give, and several nodes (or test workers) on one machine
then fight over its cores. Measured on two cores: the default pass 5.5 -> 4.8 s end to end
(``orbit-tracking bench --suite speed``), and a CPU-bound test module with two pytest
workers 77 -> 28 s.
"""

import os as _os

for _var in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
    _os.environ.setdefault(_var, '1')

__all__ = ['__version__']

__version__ = '0.1.0'

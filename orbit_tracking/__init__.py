"""orbit_tracking: trajectory estimation of flight vehicles from many tracking sensors."""

__all__ = ['__version__']

__version__ = '0.1.0'

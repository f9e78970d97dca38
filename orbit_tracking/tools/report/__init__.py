"""Plots and reports for engineers who would rather look than read topics.

:func:`build_html_report` writes ``report.html`` and its PNG figures for an output folder of
``orbit-tracking estimate`` or ``orbit-tracking demo`` (:func:`read_output_folder`):
trajectory and ground track, position and velocity errors with their ±3σ bands, post-fit
residuals per station and field, station biases with error bars and the summary figures.
What the folder alone cannot give (truth, the measurements) comes in a :class:`RunContext`,
read from a bag or simulated again from a scenario by :func:`report_context`.

Submodules (every public name is re-exported here; import from this package):

* :mod:`~orbit_tracking.tools.report.folder`: :class:`RunContext`,
  :func:`context_from_scenario`, :class:`OutputFolder`, :func:`read_output_folder`, and
  ``_Page``, the two on the report's time axis;
* :mod:`~orbit_tracking.tools.report.figures`: the ``plot_html_*`` figures (matplotlib,
  Agg) and their plotting helpers;
* :mod:`~orbit_tracking.tools.report.html`: :data:`HTML_FIGURES`, the page's sections and
  tables, :func:`build_html_report`;
* :mod:`~orbit_tracking.tools.report.inputs`: :func:`report_context`,
  :func:`context_from_bag`, :func:`find_input_bag`, :func:`output_world_frame` (bag
  contents into a :class:`RunContext`).

Only ``inputs`` reads bags (through ``rosbags`` and the message conversions); the figures
and the page need nothing from ROS.
"""

from __future__ import annotations

from orbit_tracking.tools.report.folder import (
    OutputFolder,
    RunContext,
    context_from_scenario,
    read_output_folder,
)
from orbit_tracking.tools.report.html import HTML_FIGURES, build_html_report
from orbit_tracking.tools.report.inputs import (
    context_from_bag,
    find_input_bag,
    output_world_frame,
    report_context,
)

__all__ = [
    'HTML_FIGURES',
    'OutputFolder',
    'RunContext',
    'build_html_report',
    'context_from_bag',
    'context_from_scenario',
    'find_input_bag',
    'output_world_frame',
    'read_output_folder',
    'report_context',
]

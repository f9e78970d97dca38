"""Truth and measurements for ``orbit-tracking report``: read from the bag an output
folder was estimated from, or simulated again from the scenario it names.

The rest of the report (:mod:`orbit_tracking.tools.report`) is ROS-free; this module turns
bag contents into its :class:`~orbit_tracking.tools.report.folder.RunContext`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path
from typing import Any

from orbit_tracking.core.errors import ConfigError
from orbit_tracking.core.sim.scenario import load_scenario
from orbit_tracking.ros.bag import BagError, bag_folder, read_bag
from orbit_tracking.tools.bag_inputs import BagContext, read_for_estimation
from orbit_tracking.tools.report.folder import RunContext, context_from_scenario

__all__ = ['context_from_bag', 'find_input_bag', 'output_world_frame', 'report_context']


def find_input_bag(folder: Path, summary: Mapping[str, Any] | None) -> Path | None:
    """The bag ``summary.yaml`` names (as given to ``estimate``: relative to the working
    directory then, so also tried next to the folder, e.g. a demo run's ``offline/bag/``
    beside its ``offline/estimate/``, and inside it, e.g. a demo run's ``live_bag/``); None
    if not found."""
    name = (summary or {}).get('bag')
    if not name:
        return None
    p = Path(str(name))
    others = [folder.parent / p, folder.parent / p.name, folder / p.name]
    for cand in [p] if p.is_absolute() else [p, *others]:
        if (cand / 'metadata.yaml').is_file():
            return cand
    return None


def context_from_bag(bag: str | Path) -> RunContext:
    """Measurements, station poses, truth (``truth/state``) and the simulated biases of a
    bag, on the time base ``orbit-tracking estimate`` used for it."""
    ctx = BagContext.from_custom_data(bag)
    buf, _counts = read_for_estimation(bag, ctx, progress=False)
    ctx.scenario_truth_biases()
    return RunContext(
        ctx.tb(0).ref_ns,
        f'bag {bag}' + ('' if ctx.truth else ' (no truth/state in it)'),
        ctx.world_frame,
        dict(ctx.truth),
        ctx.truth_biases,
        tuple(ctx.gaps),
        buf.observations(),
    )


def report_context(
    folder: Path,
    summary: Mapping[str, Any] | None,
    bag: str | Path | None = None,
    scenario: str | None = None,
) -> tuple[RunContext | None, list[str]]:
    """What the report of ``folder`` can know besides its files, and notes on what not.

    ``scenario`` (a name or YAML path) is simulated again and wins; otherwise the bag
    (``bag``, or the one ``summary.yaml`` names) gives the measurements and truth, and
    when it has no truth the scenario ``summary.yaml`` names gives it, if it is one of the
    package's (or a path).

    A bag found through ``summary.yaml`` that cannot be read is a note, not an error.

    Raises
    ------
    BagError, FileNotFoundError, ConfigError
        ``bag`` or ``scenario`` was given and cannot be read.
    """
    notes: list[str] = []
    if scenario:
        return context_from_scenario(load_scenario(scenario)), notes
    ctx: RunContext | None = None
    if bag is not None:
        ctx = context_from_bag(bag_folder(bag))
    else:
        path = find_input_bag(folder, summary)
        if path is None and (summary or {}).get('bag'):
            notes.append(
                f'the input bag {(summary or {})["bag"]} named in summary.yaml was not found '
                '(pass --bag BAG for residuals and truth)'
            )
        elif path is not None:
            try:
                ctx = context_from_bag(path)
            except BagError as exc:
                notes.append(f'the input bag named in summary.yaml cannot be read: {exc}')
    name = str((summary or {}).get('scenario') or '')
    if (ctx is None or not ctx.truth) and name:
        try:
            sc = context_from_scenario(load_scenario(name))
        except (FileNotFoundError, ConfigError) as exc:
            notes.append(f'no truth from scenario {name!r} of summary.yaml: {exc}')
        else:
            if ctx is None:
                ctx = sc
            else:
                dt = (sc.ref_ns - ctx.ref_ns) * 1e-9
                ctx = replace(
                    ctx,
                    source=f'{ctx.source}; truth: {sc.source}',
                    world_frame=ctx.world_frame or sc.world_frame,
                    truth={k: replace(v, time=v.time + dt) for k, v in sc.truth.items()},
                    truth_biases=(
                        sc.truth_biases if ctx.truth_biases is None else ctx.truth_biases
                    ),
                    gaps=ctx.gaps or tuple((a + dt, b + dt) for a, b in sc.gaps),
                )
    if ctx is None or not ctx.truth:
        notes.append(
            'no truth (neither truth/state in the bag nor a scenario of the package): the '
            'page shows uncertainties, not errors; --scenario NAME simulates one again'
        )
    return ctx, notes


def output_world_frame(folder: Path) -> str:
    """The world frame of the folder's own bag (``trajectory/states`` frame id), or ''."""
    if not (folder / 'bag' / 'metadata.yaml').is_file():
        return ''
    try:
        first = next(iter(read_bag(folder / 'bag', ['trajectory/states'])), None)
    except (OSError, ValueError, KeyError, BagError):
        return ''
    return str(first.msg.header.frame_id) if first is not None else ''

"""``report.html`` of an output folder: its sections (summary tables, then the figures of
:mod:`~orbit_tracking.tools.report.figures` with their captions), each replaced by a note
saying why when it cannot be drawn, and :func:`build_html_report`, which writes the page.
"""

from __future__ import annotations

import html
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402
import yaml  # noqa: E402

from orbit_tracking.tools.report.figures import (  # noqa: E402
    plot_html_biases,
    plot_html_biases_by_window,
    plot_html_errors,
    plot_html_residuals,
    plot_html_trajectory,
)
from orbit_tracking.tools.report.folder import OutputFolder, RunContext, _Page, _Skip  # noqa: E402

__all__ = ['HTML_FIGURES', 'build_html_report']

HTML_FIGURES: Mapping[str, str] = {
    'trajectory': 'trajectory.png',
    'errors': 'state_errors.png',
    'residuals': 'residuals.png',
    'biases': 'biases.png',
    'biases_by_window': 'biases_by_window.png',
}
"""PNG files :func:`build_html_report` may write next to ``report.html``."""


def _fmt(v: Any) -> str:
    if isinstance(v, bool) or v is None:
        return str(v)
    if isinstance(v, float):
        return f'{v:.6g}'
    if isinstance(v, Mapping | list | tuple):
        return yaml.safe_dump(v, default_flow_style=True, width=10_000).strip()
    return str(v)


def _table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    head = ''.join(f'<th>{html.escape(h)}</th>' for h in header)
    body = ''.join(
        '<tr>' + ''.join(f'<td>{html.escape(_fmt(c))}</td>' for c in r) + '</tr>' for r in rows
    )
    return f'<table><tr>{head}</tr>{body}</table>'


def _records(records: Sequence[Mapping[str, Any]], first: Sequence[str] = ()) -> str:
    """A table of mappings: the ``first`` keys, then every other key in order of appearance."""
    keys = list(first)
    for r in records:
        keys += [k for k in r if k not in keys]
    return _table(keys, [[r.get(k, '') for k in keys] for r in records])


def _flatten(data: Mapping[str, Any], prefix: str = '') -> list[tuple[str, Any]]:
    out: list[tuple[str, Any]] = []
    for k, v in data.items():
        if isinstance(v, Mapping) and v:
            out += _flatten(v, f'{prefix}{k}.')
        else:
            out.append((f'{prefix}{k}', v))
    return out


def _missing(text: str) -> str:
    return f'<p class="missing">{html.escape(text)}</p>'


def _img(path: Path, caption: str = '') -> str:
    return (
        f'<figure><img src="{html.escape(path.name)}" alt="{html.escape(path.stem)}">'
        f'<figcaption>{html.escape(caption)}</figcaption></figure>'
    )


def _summary_section(page: _Page, out: Path) -> str:
    s = page.out.summary
    if s is None:
        raise _Skip(page.out.problems.get('summary.yaml', 'no summary.yaml'))
    parts = [
        _table(
            ('figure', 'value'),
            _flatten({k: v for k, v in s.items() if k not in ('windows', 'evaluation', 'biases')}),
        )
    ]
    ev = s.get('evaluation') or {}
    rows = [
        {'target': tid, 'where': where.replace('_', ' '), **vals}
        for tid, parts_ in ev.items()
        for where, vals in parts_.items()
    ]
    parts += [
        '<h3>Against truth</h3>',
        _records(rows)
        if rows
        else _missing('no evaluation against truth: the bag had no truth/state'),
    ]
    windows = []
    for w in s.get('windows') or []:
        row = {k: v for k, v in w.items() if not isinstance(v, Mapping | list)}
        row['used'] = sum((w.get('used') or {}).values())
        row['rejected'] = sum((w.get('rejected') or {}).values())
        windows.append(row)
    if windows:
        parts += ['<h3>Windows</h3>', _records(windows, ('start', 'end', 'success'))]
    return '\n'.join(parts)


def _trajectory_section(page: _Page, out: Path) -> str:
    return _img(
        plot_html_trajectory(page, out / HTML_FIGURES['trajectory']),
        'Solid: the estimate (trajectory.csv); dashed: truth. Left: east/north/up from the '
        'ground point below the first state; middle: ground track; right: height.',
    )


def _errors_section(page: _Page, out: Path) -> str:
    text = (
        ''
        if any(t in page.truth for t in page.tracks)
        else _missing('no truth for the estimated targets: showing the 1σ envelope alone')
    )
    return text + _img(
        plot_html_errors(page, out / HTML_FIGURES['errors']),
        'World-frame components; bands from the s* columns of trajectory.csv; grey: '
        'incomplete segments.',
    )


def _residuals_section(page: _Page, out: Path) -> str:
    return _img(
        plot_html_residuals(page, out / HTML_FIGURES['residuals']),
        'Each measurement minus its prediction from the estimated trajectory, in units of its '
        'sigma (at most 1500 rows per station drawn). Dashed: the final estimate of an '
        'offset bias (biases.csv) in units of the median sigma of its field.',
    )


def _biases_section(page: _Page, out: Path) -> str:
    o = page.out
    if o.biases is None:
        raise _Skip(o.problems.get('biases.csv', 'no biases.csv'))
    if not o.biases:
        raise _Skip('biases.csv has no rows: the estimate declared no biases (--biases)')
    parts = [
        _img(
            plot_html_biases(page, out / HTML_FIGURES['biases']),
            'Final estimates ±1σ (biases.csv: each from the last window with rows of its '
            'station); crosses: the simulated truth, when known.',
        )
    ]
    if o.biases_by_window:
        fig = plot_html_biases_by_window(page, out / HTML_FIGURES['biases_by_window'])
        parts.append(_img(fig, "Every window's estimate ±1σ at its middle; dotted: truth."))
    else:
        parts.append(_missing(o.problems.get('biases_by_window.csv', 'no rows per window')))
    summary = (o.summary or {}).get('biases') or {}
    rows = summary.get('final') or [
        dict(zip(('station', 'field', 'bias', 'sigma'), r, strict=True)) for r in o.biases
    ]
    parts.append(_records(rows))
    parts += [_missing(str(n)) for n in summary.get('notes') or []]
    return '\n'.join(parts)


_SECTIONS: tuple[tuple[str, Callable[[_Page, Path], str]], ...] = (
    ('Summary', _summary_section),
    ('Trajectory', _trajectory_section),
    ('Position and velocity errors', _errors_section),
    ('Residuals per station and field', _residuals_section),
    ('Station biases', _biases_section),
)

_CSS = (
    'body{font-family:sans-serif;margin:1em auto;max-width:1500px;padding:0 1em}'
    'table{border-collapse:collapse;font-size:85%;margin:.5em 0}'
    'th,td{border:1px solid #bbb;padding:2px 6px;text-align:left}th{background:#eee}'
    '.missing{color:#a33;font-style:italic}img{max-width:100%}'
)


def build_html_report(
    folder: OutputFolder,
    out: str | Path | None = None,
    context: RunContext | None = None,
    notes: Sequence[str] = (),
    world_frame: str = '',
) -> Path:
    """Write ``report.html`` and its PNG figures (:data:`HTML_FIGURES`) into ``out``.

    Parameters
    ----------
    folder : OutputFolder
        What :func:`read_output_folder` read.
    out : path-like, optional
        Folder to write to (created); default the output folder itself.
    context : RunContext, optional
        Truth and measurements; without it the page shows the 1σ envelope instead of
        errors, and no residuals.
    notes : sequence of str
        Lines printed at the top (e.g. where the context came from).
    world_frame : str
        ``earth`` or ``eci`` when the context does not say (e.g. from the output bag).

    Returns
    -------
    Path
        ``report.html``. Every section that cannot be drawn says why instead; nothing is
        raised for a missing piece.
    """
    out = Path(out) if out is not None else folder.path
    out.mkdir(parents=True, exist_ok=True)
    for name in HTML_FIGURES.values():
        (out / name).unlink(missing_ok=True)  # no stale figure from an earlier report
    page = _Page.make(folder, context, world_frame)
    body = []
    for title, section in _SECTIONS:
        try:
            text = section(page, out)
        except _Skip as exc:
            text = _missing(str(exc))
        except Exception as exc:  # noqa: BLE001 -- a report shows what it can
            plt.close('all')
            text = _missing(f'could not draw this section: {type(exc).__name__}: {exc}')
        body.append(f'<section><h2>{html.escape(title)}</h2>\n{text}\n</section>')
    ref = f'{page.ref_ns // 1_000_000_000}.{page.ref_ns % 1_000_000_000:09d}'
    info = [
        f'Output folder: {folder.path.resolve()}',
        f'Time axis: seconds after stamp {ref} s.',
        f'World frame: {page.frame or "not recorded"}.',
        f'Truth and measurements: {context.source if context else "none"}.',
        *notes,
        *folder.problems.values(),
    ]
    title = f'orbit_tracking report: {folder.path.resolve().name}'
    text = (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f'<title>{html.escape(title)}</title><style>{_CSS}</style></head><body>\n'
        f'<h1>{html.escape(title)}</h1>\n<ul>'
        + ''.join(f'<li>{html.escape(line)}</li>' for line in info)
        + '</ul>\n'
        + '\n'.join(body)
        + '\n</body></html>\n'
    )
    path = out / 'report.html'
    path.write_text(text, encoding='utf-8')
    return path

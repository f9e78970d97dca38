"""What the subcommands share: one rule for the folder a command writes (refused when it
exists with something in it, unless ``--force``) and one check of the bag a command reads.
Both raise errors that :func:`orbit_tracking.tools.cli.main` prints as one line with exit
status 2."""

from __future__ import annotations

import argparse
import shutil
from collections.abc import Iterable
from pathlib import Path

from orbit_tracking.core.errors import OrbitTrackingError

__all__ = ['OutputExistsError', 'add_force', 'input_bag', 'prepare_output_folder']


class OutputExistsError(OrbitTrackingError):
    """The output folder of a command exists and is not empty, and ``--force`` was not
    given (or it would replace the command's own input)."""


def add_force(parser: argparse.ArgumentParser) -> None:
    """The ``--force`` option of a command that writes a folder (same help everywhere)."""
    parser.add_argument(
        '--force',
        action='store_true',
        help='replace the output folder if it exists and is not empty',
    )


def prepare_output_folder(out: str | Path, force: bool, inputs: Iterable[str | Path] = ()) -> Path:
    """Make ``out`` ready for a command to write: afterwards it does not exist (the
    command creates it).

    An existing empty folder is removed. An existing folder with anything in it, or a
    file, is refused unless ``force``, and then removed. A folder that is, or holds, one
    of ``inputs`` (the bag being read) or the working directory is refused even with
    ``force``.

    Raises
    ------
    OutputExistsError
    """
    out = Path(out)
    if not (out.exists() or out.is_symlink()):
        return out
    target = out.resolve()
    cwd = Path.cwd().resolve()
    if target == cwd or target in cwd.parents:
        raise OutputExistsError(f'{out} holds the working directory; choose another --out')
    for path in inputs:
        p = Path(path).resolve()
        if p == target or target in p.parents:
            raise OutputExistsError(f'{out} holds the input {path}; choose another --out')
    if out.is_dir() and not out.is_symlink():
        if any(out.iterdir()) and not force:
            raise OutputExistsError(
                f'{out} exists and is not empty; pass --force to replace it or choose another '
                '--out'
            )
        shutil.rmtree(out)
    else:
        if not force:
            raise OutputExistsError(
                f'{out} exists and is not a folder; pass --force to replace it or choose '
                'another --out'
            )
        out.unlink()
    return out


def input_bag(path: str | Path, scan: bool = False) -> Path:
    """The bag folder a command reads, checked before anything is written or started: its
    metadata, its storage files and their headers; with ``scan`` also every message's
    bytes (for a command that cannot stop cleanly half way, such as ``replay``). A bag
    without messages is refused too.

    Raises
    ------
    BagError
        ``path`` is not a readable rosbag2 (see :func:`orbit_tracking.ros.bag.bag_folder`).
    """
    from orbit_tracking.ros.bag import BagError, bag_folder, bag_topics, scan_bag

    folder = bag_folder(path)
    n = scan_bag(folder) if scan else sum(n for _, n in bag_topics(folder).values())
    if not n:
        raise BagError(f'{folder} has no messages')
    return folder

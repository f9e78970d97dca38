"""``launch/tracking.launch.py`` starts the nodes of the main job (``live.NODES``), and every
executable and parameter file it names is built and installed by ``setup.py``.

``launch`` is not on PyPI, so the launch file is read with ``ast``, never imported; setup.py
is run with ``setuptools.setup`` replaced, to see exactly what it would install.
"""

from __future__ import annotations

import ast
import runpy
import sys
from pathlib import Path
from typing import Any
from unittest import mock

import pytest

from orbit_tracking.tools.live import NODES, SIMULATOR, PackageLocation, node_command

ROOT = Path(__file__).resolve().parents[1]
LAUNCH = ROOT / 'launch' / 'tracking.launch.py'


def _launch_nodes() -> list[tuple[str, list[str]]]:
    """``(executable, parameter file names)`` of every ``Node(...)`` of the launch file, in
    order."""
    out = []
    for call in ast.walk(ast.parse(LAUNCH.read_text())):
        if not isinstance(call, ast.Call):
            continue
        func = call.func
        name = func.id if isinstance(func, ast.Name) else getattr(func, 'attr', '')
        if name != 'Node':
            continue
        kw = {k.arg: k.value for k in call.keywords}
        exe = kw['executable']
        assert isinstance(exe, ast.Constant), 'executable= must be a literal string'
        files = [
            c.value
            for c in ast.walk(kw['parameters'])
            if isinstance(c, ast.Constant) and str(c.value).endswith('.yaml')
        ]
        out.append((exe.value, files))
    return out


@pytest.fixture(scope='module')
def setup_kwargs() -> dict[str, Any]:
    """The keyword arguments setup.py gives ``setuptools.setup``."""
    with mock.patch('setuptools.setup') as setup:
        runpy.run_path(str(ROOT / 'setup.py'), run_name='__main__')
    assert setup.call_count == 1
    return dict(setup.call_args.kwargs)


def test_launch_file_starts_the_nodes_and_parameter_files_of_the_main_job():
    launched = _launch_nodes()
    assert launched, f'no Node(...) in {LAUNCH}'
    assert sorted(launched) == sorted((n.executable, [n.params_file]) for n in NODES)
    # the processing nodes listen before the simulator streams
    assert launched[-1][0] == SIMULATOR == NODES[-1].executable


def test_every_node_of_the_main_job_is_a_console_script_of_setup_py(setup_kwargs):
    scripts = dict(
        (p.strip() for p in entry.split('=', 1))
        for entry in setup_kwargs['entry_points']['console_scripts']
    )
    for node in NODES:
        assert scripts.get(node.executable) == f'orbit_tracking.ros.{node.module}:main', (
            f'{node.executable} is not the console script of orbit_tracking.ros.{node.module}'
        )
    assert 'orbit-tracking' in scripts  # the recorder of the live pass


def test_every_parameter_file_exists_and_is_installed_into_share_config(setup_kwargs):
    installed = {(dest, Path(f).name) for dest, files in setup_kwargs['data_files'] for f in files}
    for node in NODES:
        assert (ROOT / 'config' / node.params_file).is_file(), node.params_file
        assert ('share/orbit_tracking/config', node.params_file) in installed
    assert ('share/orbit_tracking/launch', LAUNCH.name) in installed


def test_node_commands_run_the_installed_executable_or_the_source_module(tmp_path):
    spec = next(n for n in NODES if n.executable == 'estimator')
    installed = PackageLocation(tmp_path / 'lib' / 'orbit_tracking', tmp_path / 'config')
    cmd = node_command(spec, installed, {'time_reference': 1.7e9, 'bias_file': 'auto'})
    assert cmd[:4] == [
        str(tmp_path / 'lib' / 'orbit_tracking' / 'estimator'),
        '--ros-args',
        '--params-file',
        str(tmp_path / 'config' / 'estimator.yaml'),
    ]
    params = [cmd[i + 1] for i, a in enumerate(cmd) if a == '-p']
    assert 'time_reference:=1700000000.0' in params and 'bias_file:=auto' in params
    source = PackageLocation(None, ROOT / 'config', ROOT)
    cmd = node_command(spec, source)
    assert cmd[:3] == [sys.executable, '-m', 'orbit_tracking.ros.estimator_node']
    assert cmd[3:6] == ['--ros-args', '--params-file', str(ROOT / 'config' / 'estimator.yaml')]

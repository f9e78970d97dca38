"""The package layout keeps its rules (docs/ARCHITECTURE.md): the numerical core never imports
ROS, the data types never import the simulator, ``ros/`` holds only what needs ROS, every
module says what it exports, and a long module says why it is long.

The imports are read with ``ast`` (every ``import`` statement, also the ones inside
functions), so a lazy import cannot slip past.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / 'orbit_tracking'
MODULES = sorted(PACKAGE.rglob('*.py'))
MAX_LINES = 600
ROS_ROOTS = frozenset(
    {
        'rclpy',
        'rosbags',
        'rosidl_runtime_py',
        'builtin_interfaces',
        'diagnostic_msgs',
        'geometry_msgs',
        'nav_msgs',
        'rcl_interfaces',
        'rosgraph_msgs',
        'sensor_msgs',
        'std_msgs',
        'std_srvs',
        'visualization_msgs',
    }
)


def _name(path: Path) -> str:
    rel = path.relative_to(PACKAGE.parent).with_suffix('')
    parts = rel.parts[:-1] if rel.name == '__init__' else rel.parts
    return '.'.join(parts)


def _imports(path: Path) -> set[str]:
    """Every module ``path`` imports (absolute names; relative imports resolved)."""
    tree = ast.parse(path.read_text(), str(path))
    here = _name(path).split('.')
    if path.name != '__init__.py':
        here = here[:-1]
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ''
            if node.level:
                base = '.'.join(here[: len(here) - node.level + 1] + ([base] if base else []))
            out.add(base)
            out.update(f'{base}.{a.name}' for a in node.names)
    return out


def _in(module: str, package: str) -> bool:
    return module == package or module.startswith(package + '.')


def _modules_under(package: str) -> list[Path]:
    return [p for p in MODULES if _in(_name(p), package)]


def test_the_package_has_the_documented_subpackages():
    for sub in (
        'core.models',
        'core.data',
        'core.sim',
        'core.triangulation',
        'core.estimation',
        'core.baselines',
        'ros',
        'ros.conversions',
        'tools',
        'tools.bench',
        'tools.commands',
        'tools.report',
    ):
        assert (PACKAGE / sub.replace('.', '/') / '__init__.py').is_file(), sub


@pytest.mark.parametrize('path', _modules_under('orbit_tracking.core'), ids=_name)
def test_core_never_imports_ros_or_the_tools(path: Path):
    bad = sorted(
        m
        for m in _imports(path)
        if m.split('.')[0] in ROS_ROOTS
        or _in(m, 'orbit_tracking.ros')
        or _in(m, 'orbit_tracking.tools')
    )
    assert not bad, f'{_name(path)} imports {bad}'


@pytest.mark.parametrize('path', _modules_under('orbit_tracking.core.data'), ids=_name)
def test_data_types_never_import_the_simulator(path: Path):
    bad = sorted(m for m in _imports(path) if _in(m, 'orbit_tracking.core.sim'))
    assert not bad, f'{_name(path)} imports {bad}'


@pytest.mark.parametrize(
    'path', [p for p in _modules_under('orbit_tracking.ros') if p.name != '__init__.py'], ids=_name
)
def test_ros_modules_need_ros(path: Path):
    """A module of ``ros/`` uses ROS itself (rclpy, rosbags or a message package) or builds
    on another ``ros/`` module; ROS-free code belongs in ``core/`` or ``tools/``."""
    imports = _imports(path)
    assert any(
        m.split('.')[0] in ROS_ROOTS or (_in(m, 'orbit_tracking.ros') and m != _name(path))
        for m in imports
    ), f'{_name(path)} runs without ROS: move it out of ros/'


@pytest.mark.parametrize('path', MODULES, ids=_name)
def test_every_module_declares_all_and_says_what_it_is(path: Path):
    tree = ast.parse(path.read_text(), str(path))
    assert ast.get_docstring(tree), f'{_name(path)} has no module docstring'
    names = {
        t.id
        for node in tree.body
        if isinstance(node, (ast.Assign, ast.AnnAssign))
        for t in (node.targets if isinstance(node, ast.Assign) else [node.target])
        if isinstance(t, ast.Name)
    }
    assert '__all__' in names, f'{_name(path)} has no __all__'


@pytest.mark.parametrize('path', MODULES, ids=_name)
def test_a_long_module_states_why_at_its_top(path: Path):
    n = len(path.read_text().splitlines())
    if n <= MAX_LINES:
        return
    doc = ast.get_docstring(ast.parse(path.read_text())) or ''
    assert '600-line' in doc, (
        f'{_name(path)} has {n} lines: split it, or say at its top why it is longer than '
        f'the ~{MAX_LINES}-line guide'
    )


def test_every_public_name_in_all_exists():
    import importlib

    for path in MODULES:
        mod = importlib.import_module(_name(path))
        missing = [n for n in getattr(mod, '__all__', ()) if not hasattr(mod, n)]
        assert not missing, f'{_name(path)}.__all__ names {missing}, which it does not define'

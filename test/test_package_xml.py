"""The ROS manifest (package.xml) parses, declares an ament_python package, and every
dependency it declares is available in this environment.

colcon-ros decides the build type from package.xml: if catkin_pkg cannot parse it (an invalid
e-mail address is enough), colcon silently builds a plain Python package without the ament
hooks, and ``ros2 run`` / ``ament_index_python`` cannot find it. This test catches that early.
"""

import ast
import importlib
import importlib.util
import types
from pathlib import Path

import pytest
from catkin_pkg.package import Package, parse_package

ROOT = Path(__file__).resolve().parents[1]
PKG = 'orbit_tracking'

# rosdep keys of Python libraries -> the module they provide.
ROSDEP_PYTHON_MODULES = {
    'python3-numpy': 'numpy',
    'python3-scipy': 'scipy',
    'python3-yaml': 'yaml',
    'python3-matplotlib': 'matplotlib',
    'python3-cryptography': 'cryptography',
    'python3-pytest': 'pytest',
}
# ROS packages providing Python modules of the same name (not interface packages).
ROS_PYTHON_PACKAGES = {'rclpy', 'ament_index_python'}
INTERFACE_SUFFIXES = ('_msgs', '_srvs', '_interfaces')


def _manifest() -> Package:
    return parse_package(str(ROOT / 'package.xml'))


def _is_interface_package(name: str) -> bool:
    return name.endswith(INTERFACE_SUFFIXES)


EXEC_DEPENDS = sorted(d.name for d in _manifest().exec_depends)
TEST_DEPENDS = sorted(d.name for d in _manifest().test_depends)


def test_manifest_parses_as_format3_ament_python() -> None:
    warnings: list[str] = []
    pkg = parse_package(str(ROOT / 'package.xml'), warnings=warnings)
    assert warnings == [], f'catkin_pkg warnings for package.xml: {warnings}'
    assert pkg.package_format == 3
    assert pkg.name == PKG
    assert pkg.get_build_type() == 'ament_python'
    assert pkg.licenses == ['Apache-2.0']
    assert pkg.maintainers and all(m.email for m in pkg.maintainers)
    # The resource-index marker that setup.py installs must exist and be named after the package.
    assert (ROOT / 'resource' / PKG).is_file()


def _literal_kwarg(tree: ast.AST, func: str, kwarg: str) -> object:
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and getattr(node.func, 'id', None) == func:
            for kw in node.keywords:
                if kw.arg == kwarg:
                    return ast.literal_eval(kw.value)
    raise AssertionError(f'{func}({kwarg}=...) not found')


def test_versions_agree() -> None:
    xml_version = _manifest().version
    setup_version = _literal_kwarg(ast.parse((ROOT / 'setup.py').read_text()), 'setup', 'version')
    init_tree = ast.parse((ROOT / PKG / '__init__.py').read_text())
    init_version = next(
        ast.literal_eval(n.value)
        for n in ast.walk(init_tree)
        if isinstance(n, ast.Assign)
        and any(getattr(t, 'id', '') == '__version__' for t in n.targets)
    )
    assert xml_version == setup_version == init_version, (
        f'package.xml {xml_version}, setup.py {setup_version}, __init__.py {init_version}'
    )


def _interface_modules(name: str) -> list[types.ModuleType]:
    importlib.import_module(name)
    return [
        importlib.import_module(f'{name}.{kind}')
        for kind in ('msg', 'srv', 'action')
        if importlib.util.find_spec(f'{name}.{kind}') is not None
    ]


@pytest.mark.parametrize('name', EXEC_DEPENDS + TEST_DEPENDS)
def test_dependency_available(name: str) -> None:
    if _is_interface_package(name):
        modules = _interface_modules(name)
        assert modules, f'{name} has no msg/srv/action module'
        # Load the C type support the way rclpy does when creating a publisher/service.
        from rosidl_generator_py import import_type_support

        import_type_support(name)
        for module in modules:
            classes = [
                obj
                for _attr, obj in sorted(vars(module).items())
                if isinstance(obj, type) and hasattr(type(obj), '__import_type_support__')
            ]
            assert classes, f'{module.__name__} defines no interface classes'
            cls = classes[0]
            type(cls).__import_type_support__()
            assert type(cls)._TYPE_SUPPORT is not None, f'no type support for {cls}'
    elif name in ROS_PYTHON_PACKAGES:
        importlib.import_module(name)
    elif name in ROSDEP_PYTHON_MODULES:
        importlib.import_module(ROSDEP_PYTHON_MODULES[name])
    else:
        pytest.fail(
            f'package.xml depends on {name!r}, which this test does not know how to check: '
            'add it to ROSDEP_PYTHON_MODULES / ROS_PYTHON_PACKAGES (and to requirements.txt)'
        )

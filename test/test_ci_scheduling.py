"""The test run's own scheduling (test/conftest.py): the tests of a module that starts DDS
processes are one work unit for pytest-xdist, every other test is its own."""

from __future__ import annotations

from conftest import DdsModulesTogether


def test_a_dds_module_is_one_scope_and_any_other_test_its_own() -> None:
    split = DdsModulesTogether._split_scope
    for nodeid in (
        'test/test_faults.py::test_fault_is_rejected_counted_and_leaves_the_trajectory_unchanged[x]',
        'test/test_faults.py::test_every_class_builds_its_messages_on_the_topics_it_declares',
        'test/test_package_build.py::test_node_executable_starts[estimator]',
    ):
        assert split(None, nodeid) == nodeid.split('::')[0]  # type: ignore[arg-type]
    for nodeid in (
        'test/test_wire.py::test_parse_cloud_reads_what_rclpy_reads[3]',
        'test/nope.py::t',
    ):
        assert split(None, nodeid) == nodeid  # type: ignore[arg-type]

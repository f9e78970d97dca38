"""Fault injection over real DDS (issue 13): every class of bad input in
``orbit_tracking/tools/bench/fault_catalogue.py`` is published by a separate participant
into a replay of ``test/data/bags/seed000_s1_20_50`` through the running
``triangulation``, ``estimator`` and ``results`` nodes (each its own process, the test
run's DDS domain and a second one for a parallel lane, discovery on localhost).

For each class: no node dies, hangs or logs a traceback; every node the class targets
counts the rejection in its ``/diagnostics`` (some rejection counter grew; which one is
recorded, names may change); and the replay's ``trajectory/states`` equal the clean
replay's (the same states, positions within 1e-6 m).

The classes share a few replays (one per group of the catalogue, two at a time); a class
that breaks its replay is found by re-running it alone (see
``orbit_tracking/tools/bench/faults.py``). All the replays run once, in the first test
that needs them, for the classes selected in this session (``-k`` selects fewer). One
extra class, ``control_plausible_point``, is a plausible measurement the nodes must use:
the suite has to report it as changing the trajectory, or its checks prove nothing.
"""

from __future__ import annotations

import pytest

from orbit_tracking.tools.bench.fault_catalogue import CATALOGUE, CONTROL

NAMES = [f.name for f in CATALOGUE]
BUDGET_S = 900.0
"""Wall seconds after which no further replay starts (the classes left are reported not
run). When every class passes the suite is six replays, two at a time; each class that
breaks its group's replay costs one replay per class of the group."""


@pytest.fixture(scope='module')
def fault_results(request, tmp_path_factory):
    """name -> FaultResult for every class this session selected (one suite run)."""
    from orbit_tracking.tools.bench.faults import run_faults

    wanted = set()
    for item in request.session.items:
        if item.module is request.module and hasattr(item, 'callspec'):
            wanted.add(item.callspec.params.get('name'))
    wanted.discard(None)
    if any(item.name.startswith('test_the_suite_') for item in request.session.items):
        wanted.add(CONTROL.name)
    faults = [f for f in (*CATALOGUE, CONTROL) if f.name in wanted]
    suite = run_faults(
        faults,
        log_dir=tmp_path_factory.mktemp('faults'),
        budget_s=BUDGET_S,
        progress=print,
    )
    return {r.fault.name: r for r in suite.results}


def test_every_class_builds_its_messages_on_the_topics_it_declares():
    """Without DDS: each class's builder, fed the bag's messages up to its stop, gives
    messages of the right type on topics the injector will have waited for."""
    from rclpy.serialization import deserialize_message

    from orbit_tracking.ros.bag import message_class
    from orbit_tracking.tools.bench.fault_messages import Reference, topic_type
    from orbit_tracking.tools.bench.fault_replay import load_bag

    bag = load_bag()
    for f in (*CATALOGUE, CONTROL):
        until = bag.epoch_ns + int(round(f.at * 1e9))
        latest = {}
        for m in bag.messages:
            if m.measurement and m.stamp_ns >= until:
                break
            latest[m.topic] = m
        ref = Reference(
            f.at,
            bag.epoch_ns,
            {t: deserialize_message(m.raw, message_class(m.msgtype)) for t, m in latest.items()},
            bag.truth,
        )
        out = f.build(ref)
        assert out, f.name
        for inj in out:
            assert inj.topic in f.topics, (f.name, inj.topic)
            assert isinstance(inj.msg, topic_type(inj.topic)), (f.name, type(inj.msg))


def _details(r) -> str:
    counted = '; '.join(f'{n}: {list(k) or "none"}' for n, k in r.counted.items())
    return (
        f'{r.fault.name} ({r.fault.what}), decided {r.run}: sent {r.sent}, counted '
        f'[{counted}] {r.counted_how}, states {r.states} (clean {r.clean_states}, '
        f'{r.missing_states} missing, {r.extra_states} extra), largest position difference '
        f'{r.max_dp_m:.3g} m, symptoms [{r.symptoms}]; node logs in {r.logs}'
    )


@pytest.mark.dds
@pytest.mark.timeout(BUDGET_S + 300)
@pytest.mark.parametrize('name', NAMES)
def test_fault_is_rejected_counted_and_leaves_the_trajectory_unchanged(name, fault_results):
    r = fault_results[name]
    failures = []
    if r.crash:
        failures.append(f'node crash: {r.crash}')
    for node in r.fault.targets:
        if not r.counted.get(node):
            failures.append(f'{node} counted no rejection in /diagnostics')
    if r.states < 0:
        failures.append('the replay ended before the trajectory was complete')
    elif r.missing_states or r.extra_states:
        failures.append(
            f'{r.states} trajectory states, the clean replay {r.clean_states}: '
            f'{r.missing_states} missing, {r.extra_states} extra'
        )
    if not r.max_dp_m <= 1e-6:
        failures.append(f'positions differ from the clean replay by up to {r.max_dp_m:.3g} m')
    assert not failures, '\n'.join([_details(r), *failures])


@pytest.mark.dds
@pytest.mark.timeout(BUDGET_S + 300)
def test_the_suite_sees_a_message_the_nodes_use(fault_results):
    """The control: a plausible measurement is used, so the suite must see the trajectory
    move and no rejection counted (else its passes prove nothing)."""
    r = fault_results[CONTROL.name]
    assert not r.crash, _details(r)
    assert not r.counted.get('estimator'), _details(r)
    assert r.states == r.clean_states and not r.missing_states, _details(r)
    assert 1e-6 < r.max_dp_m < 100.0, _details(r)

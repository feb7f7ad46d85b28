"""A pytest plugin: per test, the seconds and number of JAX's compilations, tracings and
lowerings (``jax.monitoring`` duration events), to find where the test suite's time goes.

    PYTHONPATH=benchmarks PROBE_OUT=/tmp/probe python -m pytest -q -n 2 --dist loadfile \\
        -p compile_probe

writes ``/tmp/probe_<worker>.json`` (one list of rows per xdist worker: ``test``, ``start``
(epoch s, for the workers' timelines), ``wall`` s and,
per event, its seconds and ``n:<event>`` count). Subprocesses of tests are not seen. The
default test run's wall time is in docs/benchmarks.md (its introduction).
"""

import collections
import json
import os
import time

import pytest

_seconds: dict[str, float] = collections.defaultdict(float)
_counts: dict[str, int] = collections.defaultdict(int)
_rows: list[dict] = []


def _listener(event, duration, **_):
    _seconds[event] += duration
    _counts[event] += 1


def pytest_configure(config):
    import jax.monitoring

    jax.monitoring.register_event_duration_secs_listener(_listener)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    seconds_before, counts_before = dict(_seconds), dict(_counts)
    t0 = time.time()
    yield
    row = {"test": item.nodeid, "start": t0, "wall": time.time() - t0}
    for event in _seconds:
        row[event] = _seconds[event] - seconds_before.get(event, 0.0)
        row["n:" + event] = _counts[event] - counts_before.get(event, 0)
    _rows.append(row)


def pytest_sessionfinish(session):
    out = os.environ.get("PROBE_OUT", "/tmp/probe")
    worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
    with open(f"{out}_{worker}.json", "w") as fh:
        json.dump(_rows, fh)

"""Shared fixtures. ``run_graph`` launches real graphs (see tests/graphtools.py)."""
import os
import sys
from pathlib import Path

import pytest

os.environ.setdefault("MUJOCO_GL", "egl")  # before any test module imports mujoco
sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
# a few test modules share helpers with another folder's (``from test_ros_bag import ...``): every
# folder on the path, so that one folder runs alone as in the whole suite
for _folder in sorted(Path(__file__).resolve().parent.iterdir()):
    if _folder.is_dir() and any(_folder.glob("test_*.py")):
        sys.path.insert(0, str(_folder))

from graphtools import free_port as _free_port  # noqa: E402
from graphtools import launch_graph


LAYERS_SLOW = ("graph", "browser", "netns", "training")


def pytest_collection_modifyitems(config, items):
    """A test that launches a graph (the ``run_graph`` fixture) is ``graph``; ``graph``,
    ``browser``, ``netns`` and ``training`` tests are ``slow`` too (``-m "not slow"`` is the
    fast loop)."""
    for item in items:
        if "run_graph" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.graph)
        if any(item.get_closest_marker(m) for m in LAYERS_SLOW):
            item.add_marker(pytest.mark.slow)


@pytest.fixture
def free_port():
    """A free TCP port on 127.0.0.1."""
    return _free_port()


@pytest.fixture
def run_graph(tmp_path):
    """``run_graph(graph, args=(), wait=True, timeout=40) -> RunningGraph``: launch a graph (dict,
    YAML text or path) on a free port through ``needletrack launch``; every graph started is
    stopped at teardown, and the test fails if a node process outlives its launcher."""
    started = []

    def start(graph, **kw):
        g = launch_graph(graph, tmp_path / f"graph{len(started)}", **kw)
        started.append(g)
        return g
    yield start
    errors = []
    for g in started:
        try:
            g.stop()
        except AssertionError as exc:
            errors.append(str(exc))
    assert not errors, "\n".join(errors)

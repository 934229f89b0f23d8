"""A warm spare (``spare: true``, common/runtime/launcher.py): a second process of the node, set up
and idle (no liveliness token, no stats, no output), takes over at once when the node's process
dies; issue 32's camera restart after kill -9 (3.4 s to the next pose; ``needletrack bench
restart`` prints the figure)."""
import os
import signal
import time

from common.runtime.graph_checks import validate_graph
from common.runtime.messages import EcmJoints

GRAPH = {"nodes": [
    {"id": "count", "module": "counter", "params": {"rate_hz": 20}, "spare": True},
    {"id": "relay", "module": "relay", "inputs": {"in": "count/out"}},
]}


def test_spare_validation():
    def errs(node):
        return validate_graph({"graph": "g", "nodes": [node]})
    assert errs({"id": "c", "module": "counter", "spare": True}) == []
    assert errs({"id": "c", "module": "counter", "spare": "yes"}) == ["nodes[0].spare: expected true or false, got 'yes'"]
    need = "nodes[0].spare: a spare needs a module node that is restarted (restart: on-failure or always)"
    assert errs({"id": "c", "module": "counter", "spare": True, "restart": "never"}) == [need]
    assert errs({"id": "c", "command": ["true"], "spare": True}) == [need]


def test_a_killed_node_s_spare_takes_over_at_once(run_graph):
    g = run_graph(GRAPH)
    first = g.pids()["count"]
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and "spare ready" not in g.log():
        time.sleep(0.2)
    assert "[launcher] count: spare pid" in g.log() and "spare ready" in g.log(), g.log()[-3000:]
    spare = int(g.log().split("[launcher] count: spare pid ")[1].split()[0])
    time.sleep(1.5)
    assert g.live() == {"count", "relay"} and g.stats("count").pid == first     # the spare is unseen
    sub = g.subscribe("relay/out", EcmJoints)
    old = sub.wait(1, 20)[-1].epoch
    os.kill(first, signal.SIGKILL)
    sub.wait(3, 20, where=lambda m: m.epoch != old)
    assert g.pids()["count"] == spare
    assert f"count exited with killed by SIGKILL; spare pid {spare} took over (restart #1)" in g.log()
    st = g.wait_stats("count", lambda s: s.pid == spare, timeout=20)
    assert st.counters["restarts"] == 1 and st.counters["state"] == "active"
    # the next spare follows, and a swap replaces it (it was set up with the old spec)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and g.log().count("[launcher] count: spare pid") < 2:
        time.sleep(0.2)
    assert g.log().count("[launcher] count: spare pid") == 2, g.log()[-3000:]
    second = int(g.log().split("[launcher] count: spare pid ")[2].split()[0])
    res = g.swap("count", rate_hz=25)
    assert res.returncode == 0, res.stdout + res.stderr
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        try:
            os.kill(second, 0)
        except ProcessLookupError:
            break
        time.sleep(0.2)
    else:
        raise AssertionError(f"the spare {second} set up with the old spec outlived the swap")
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and g.log().count("[launcher] count: spare pid") < 3:
        time.sleep(0.2)
    assert g.log().count("[launcher] count: spare pid") == 3, g.log()[-3000:]

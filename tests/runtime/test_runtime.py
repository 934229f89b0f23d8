"""The node runtime and the launcher: unit tests of the pieces, then real graphs on loopback."""
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from graphtools import REPO, cli, prepare_graph

from common.runtime.graph import load_graph
from common.runtime.messages import EcmJoints, Keypoints, encode
from common.runtime.inputs import InputQueue
from common.runtime.node import Node, NodeError
from common.runtime.process import Runtime, Stats

COUNTER_RELAY = {"nodes": [
    {"id": "count", "module": "counter", "params": {"rate_hz": 40}},
    {"id": "relay", "module": "relay", "inputs": {"in": "count/out"}},
]}


# ------------------------------------------------------------------ pieces, no network

def test_newest_only_input_keeps_the_newest_and_counts_drops():
    q = InputQueue(keep_all=["calib"])
    for i in range(5):
        q.put("left", i)
    q.put("calib", "c0")
    q.put("calib", "c1")
    assert q.get(0) == ("left", 4)
    assert q.get(0) == ("calib", "c0")
    assert q.get(0) == ("calib", "c1")
    assert q.get(0) is None
    assert q.dropped["left"] == 4 and q.dropped["calib"] == 0


def test_keep_all_input_is_bounded_and_counts_what_it_drops():
    q = InputQueue(keep_all=["a"], limit=3)
    for i in range(5):
        q.put("a", i)
    assert [q.get(0)[1] for _ in range(3)] == [2, 3, 4]
    assert q.dropped["a"] == 2 and len(q) == 0


def test_inputs_are_served_in_arrival_order():
    q = InputQueue(keep_all=["k"])
    q.put("a", 1)
    q.put("k", 2)
    q.put("b", 3)
    q.put("a", 4)        # replaces 1, keeps a's place in the order
    assert [q.get(0) for _ in range(3)] == [("a", 4), ("k", 2), ("b", 3)]


def test_stats_percentiles_and_rates():
    st = Stats()
    for ms in range(1, 101):
        st.proc(float(ms))
    st.add("in.left", 10)
    counters, rates, p50, p99 = st.snapshot()
    assert counters["in.left"] == 10 and rates["in.left"] > 0
    assert p50 == 51.0 and p99 == 100.0


class _Doubler(Node):
    INPUTS = {"x": EcmJoints}
    OUTPUTS = ("y",)

    def setup(self):
        self.k = self.params.get("k", 2.0)

    def on_x(self, msg):
        self.count("seen")
        self.publish("y", EcmJoints(msg.seq, msg.stamp_ns, msg.q * self.k))


def test_offline_node_collects_what_it_publishes():
    node = _Doubler.offline(params={"k": 3.0})
    node.on_x(EcmJoints(1, 0, np.ones(4)))
    [(out, msg)] = node.published
    assert out == "y" and np.allclose(msg.q, 3.0) and node.counters["seen"] == 1
    assert node.wired("x") and not _Doubler.offline(wired=[]).wired("x")
    with pytest.raises(NodeError, match="not in OUTPUTS"):
        node.publish("z", msg)


def _graph(nodes):
    return load_graph({"graph": "unit", "nodes": nodes})


def test_runtime_refuses_wiring_the_node_class_does_not_have():
    g = _graph([{"id": "c", "module": "counter"},
                {"id": "d", "command": ["true"], "inputs": {"nope": "c/out"}, "outputs": ["zz"]}])
    rt = Runtime(g, "d")
    with pytest.raises(NodeError) as err:
        rt.build(_Doubler)
    assert "input 'nope'" in str(err.value) and "output 'zz'" in str(err.value)


def test_a_payload_of_the_wrong_type_is_a_decode_error_not_a_crash():
    g = _graph([{"id": "c", "module": "counter"}, {"id": "d", "command": ["true"], "inputs": {"x": "c/out"}}])
    rt = Runtime(g, "d")
    node = rt.build(_Doubler)
    node.setup()
    rt._pubs = {"y": _FakePub([], "y")}
    rt._dispatch("x", ("g/c/out", encode(Keypoints.not_found("left", 1, 0, "x", "wrong type")), 0.0))
    rt._dispatch("x", ("g/c/out", b"\xc1", 0.0))
    rt._dispatch("x", ("g/c/out", encode(EcmJoints(3, 0, np.ones(4))), 0.0))
    counters = rt.stats.snapshot()[0]
    assert counters["decode_errors"] == 2 and counters["in.x"] == 3 and counters["out.y"] == 1


class _FakePub:
    def __init__(self, sent, out):
        self.sent, self.out = sent, out

    def put(self, payload):
        self.sent.append((self.out, payload))


TOKEN = "0123456789abcdef0123456789abcdef"


def _ctl(**body) -> bytes:
    """A handover/takeover payload with the runtime's control token."""
    return json.dumps({"token": TOKEN, **body}).encode()


class _FakeQuery:
    def __init__(self, payload=None):
        self.key_expr = "k"
        self.payload = None if payload is None else type("P", (), {"to_bytes": lambda s: payload})()
        self.answer = None

    def reply(self, key, data):
        self.answer = json.loads(data)


def _runtime(standby, sent, token=TOKEN):
    g = _graph([{"id": "c", "module": "counter"}, {"id": "d", "command": ["true"], "inputs": {"in": "c/out"}}])
    rt = Runtime(g, "d", standby=standby, ctl_token=token)
    rt.build(_DoublerAny)
    rt._pubs = {"y": _FakePub(sent, "y")}
    return rt


class _DoublerAny(_Doubler):
    INPUTS = {"in": None}
    OUTPUTS = ("y",)

    def on_in(self, msg):
        self.publish("y", msg)


def test_handover_never_publishes_a_seq_twice_and_leaves_no_gap():
    old_sent, new_sent = [], []
    old, new = _runtime(False, old_sent), _runtime(True, new_sent)
    frame = lambda s: EcmJoints(s, 0, np.zeros(4))   # noqa: E731
    for s in range(0, 10):
        old.publish("y", frame(s))
    for s in range(7, 12):           # the standby is a little ahead: holds 7..11
        new.publish("y", frame(s))
    assert new_sent == [] and new._produced
    q = _FakeQuery(_ctl())
    old._q_handover(q)
    assert q.answer == {"ok": True, "cuts": {"y": 10}}
    old.publish("y", frame(10))      # too late: the old process no longer publishes
    q2 = _FakeQuery(_ctl(cuts=q.answer["cuts"]))
    new._q_takeover(q2)
    new.publish("y", frame(9))       # a stale frame after takeover is not published either
    new.publish("y", frame(12))
    seqs = [s for s in range(0, 10)] + [10, 11, 12]
    from common.runtime.messages import decode
    got = [decode(p).seq for _, p in old_sent] + [decode(p).seq for _, p in new_sent]
    assert got == seqs
    assert q2.answer["flushed"] == 2


def test_a_handover_or_takeover_without_the_control_token_is_refused():
    """Issue 32: one query on @ctl/<node>/<pid>/handover silenced a node for good. Only the
    launcher that started the process knows its token, and sends it only in a swap."""
    sent = []
    rt = _runtime(False, sent)
    standby = _runtime(True, [])
    for payload in (None, b"", b"\xff\xfe", b"[1]", json.dumps({"token": "x" * 32}).encode(),
                    json.dumps({"token": 5}).encode(), json.dumps({"cuts": {"y": 0}}).encode()):
        for target, op in ((rt, rt._q_handover), (standby, standby._q_takeover)):
            q = _FakeQuery(payload)
            op(q)
            assert q.answer["ok"] is False and "refused" in q.answer["error"]
    assert rt.state == "active" and standby.state == "standby"
    assert rt.stats.counters["ctl_refused"] == 7 and standby.stats.counters["ctl_refused"] == 7
    rt.publish("y", EcmJoints(3, 0, np.zeros(4)))
    assert len(sent) == 1                                   # still publishing
    untokened = _runtime(False, [], token=None)             # not started by a launcher: never
    q = _FakeQuery(_ctl())
    untokened._q_handover(q)
    assert q.answer["ok"] is False and untokened.state == "active"


class _Source(_DoublerAny):
    def step(self):
        return True


def test_a_swapped_source_starts_its_own_sequence():
    sent = []
    g = _graph([{"id": "c", "module": "counter"}, {"id": "d", "command": ["true"], "inputs": {"in": "c/out"}}])
    rt = Runtime(g, "d", standby=True, ctl_token=TOKEN)
    rt.build(_Source)
    rt._pubs = {"y": _FakePub(sent, "y")}
    for s in (0, 1):
        rt.publish("y", EcmJoints(s, 0, np.zeros(4)))
    rt._q_takeover(_FakeQuery(_ctl(cuts={"y": 500})))
    rt.publish("y", EcmJoints(2, 0, np.zeros(4)))
    from common.runtime.messages import decode
    assert [decode(p).seq for _, p in sent] == [1, 2]


# ------------------------------------------------------------------ real graphs

def test_graph_delivers_messages_end_to_end(run_graph):
    g = run_graph(COUNTER_RELAY)
    msgs = g.collect("relay/out", n=15, timeout=15, expect=EcmJoints)
    seqs = [m.seq for m in msgs]
    assert seqs == list(range(seqs[0], seqs[0] + 15))
    assert all(m.q[0] == m.seq for m in msgs)      # the payload made it through intact
    st = g.stats("relay")
    assert st.counters["in.in"] > 0 and st.counters["decode_errors"] == 0
    assert st.counters["handler_errors"] == 0 and st.rates_hz["out.out"] > 0
    assert g.live() == {"count", "relay"}


def test_one_output_fans_out_to_two_consumers_that_both_get_every_message(run_graph):
    g = run_graph({"nodes": [
        {"id": "count", "module": "counter", "params": {"rate_hz": 50}},
        {"id": "a", "module": "relay", "inputs": {"in": "count/out"}},
        {"id": "b", "module": "relay", "inputs": {"in": "count/out"}}]})
    sa, sb = g.subscribe("a/out"), g.subscribe("b/out")
    sa.wait(40, 20)
    sb.wait(40, 20)
    a = [m.seq for m in sa.messages]
    b = [m.seq for m in sb.messages]
    lo, hi = max(a[0], b[0]), min(a[-1], b[-1])
    assert hi - lo >= 30
    window = list(range(lo, hi + 1))
    assert [s for s in a if lo <= s <= hi] == window
    assert [s for s in b if lo <= s <= hi] == window


def test_a_killed_node_is_restarted_and_the_stream_resumes(run_graph):
    g = run_graph(COUNTER_RELAY)
    g.collect("relay/out", n=3, timeout=10)
    pid = g.pids()["relay"]
    os.kill(pid, signal.SIGKILL)
    sub = g.subscribe("relay/out")
    g.wait_stats("relay", lambda st: st.pid != pid, timeout=20)
    sub.wait(5, timeout=15)
    status = {r["node"]: r for r in g.status()["nodes"]}
    assert status["relay"]["restarts"] == 1 and status["relay"]["pid"] != pid
    assert status["count"]["restarts"] == 0
    assert g.stats("relay").counters["restarts"] == 1
    assert "relay exited with killed by SIGKILL; restart #1" in g.log()


def test_swap_changes_the_implementation_with_at_most_one_frame_missing(run_graph):
    g = run_graph({"nodes": [
        {"id": "count", "module": "counter", "params": {"rate_hz": 25}},
        {"id": "det", "module": "tagger", "params": {"tag": "A"}, "inputs": {"in": "count/out"}}]})
    sub = g.subscribe("det/out", Keypoints)
    sub.wait(5, 10)
    old_pid = g.pids()["det"]
    res = g.swap("det", tag="B")
    assert res.returncode == 0, res.stderr
    assert "swapped det" in res.stdout
    sub.wait(10, 15, where=lambda m: m.detector == "B")
    msgs = list(sub.messages)
    seqs, tags = [m.seq for m in msgs], [m.detector for m in msgs]
    assert len(set(seqs)) == len(seqs), "a frame was published twice"
    assert seqs == sorted(seqs)
    switch = tags.index("B")
    assert set(tags[:switch]) == {"A"} and set(tags[switch:]) == {"B"}
    assert seqs[switch] - seqs[switch - 1] <= 2, f"gap at the swap: {seqs[switch - 1]} -> {seqs[switch]}"
    assert g.pids()["det"] != old_pid
    assert g.wait_stats("det", lambda st: st.pid != old_pid).counters["handler_errors"] == 0


def test_swap_to_an_unknown_module_fails_and_the_graph_keeps_running(run_graph):
    g = run_graph(COUNTER_RELAY)
    pid = g.pids()["relay"]
    res = g.swap("relay", module="no_such_module")
    assert res.returncode == 2
    assert "unknown module 'no_such_module'" in res.stderr
    assert g.pids()["relay"] == pid
    g.collect("relay/out", n=3, timeout=10)


def test_malformed_payloads_and_raising_handlers_are_counted_and_the_node_keeps_running(run_graph):
    g = run_graph({"nodes": [
        {"id": "count", "module": "counter", "params": {"rate_hz": 40}},
        {"id": "det", "module": "tagger", "params": {"fail_every": 4}, "inputs": {"in": "count/out"}}]})
    g.collect("det/out", n=2, timeout=10)
    g.put("count/out", b"\x00not msgpack")
    st = g.wait_stats("det", lambda st: st.counters["decode_errors"] >= 1 and st.counters["handler_errors"] >= 2)
    assert st.counters["decode_errors"] == 1
    msgs = g.collect("det/out", n=5, timeout=10)
    assert all(m.seq % 4 for m in msgs)
    log = g.log()
    assert f"{g.name}/count/out: cannot decode payload" in log
    assert "on_in raised RuntimeError: failing on purpose" in log


def test_an_invalid_graph_is_refused_with_every_error_listed(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("graph: g\nnodes:\n  - {id: a, module: counter, restrat: always}\n"
                   "  - {id: b, module: relay, inputs: {in: detektor/out}}\n"
                   "  - {id: b, module: nowhere}\n")
    res = cli("launch", bad, timeout=30)
    assert res.returncode == 2
    for text in ("nodes[0].restrat: unknown key", "nodes[1].inputs.in: no node 'detektor'",
                 "nodes[2].id: duplicate id 'b'", "nodes[2].module: unknown module 'nowhere'"):
        assert text in res.stderr
    v = cli("validate", bad)
    assert v.returncode == 2 and "4 error(s)" in v.stderr


def test_a_finished_source_can_end_the_graph_and_nothing_is_left_behind(tmp_path):
    path = prepare_graph({"nodes": [
        {"id": "count", "module": "counter", "params": {"rate_hz": 100, "count": 20}, "restart": "on-failure"},
        {"id": "relay", "module": "relay", "inputs": {"in": "count/out"}}]}, tmp_path)
    res = cli("launch", path, "--until", "count", timeout=60)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "count finished: stopping the graph" in res.stdout
    assert "[count] INFO source finished" in res.stdout


def test_only_splits_a_graph_over_two_launchers(run_graph):
    g = run_graph(COUNTER_RELAY, args=["--only", "count"])
    assert g.live() == {"count"}
    env = dict(os.environ, PYTHONPATH=str(REPO))
    other = subprocess.Popen([sys.executable, "-m", "common.cli", "launch", str(g.path), "--only", "relay"],
                             cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        msgs = g.collect("relay/out", n=5, timeout=20)
        assert len(msgs) == 5
    finally:
        other.send_signal(signal.SIGTERM)
        out, _ = other.communicate(timeout=20)
    assert other.returncode == 0, out
    assert "joining the graph" in out


def test_cli_tools_see_the_running_graph(run_graph):
    g = run_graph(COUNTER_RELAY)
    ps = g.cli("ps", "--json")
    assert ps.returncode == 0, ps.stderr
    rows = {r["node"]: r for r in json.loads(ps.stdout)}
    assert set(rows) == {"count", "relay"} and rows["relay"]["live"]
    assert rows["count"]["out_hz"] > 0 and rows["relay"]["decode_errors"] == 0
    echo = g.cli("echo", "relay/out", "-n", "2", "--timeout", "10")
    assert echo.returncode == 0 and echo.stdout.count("EcmJoints(seq=") == 2
    hz = g.cli("hz", "count/out", "--duration", "2.5")
    assert hz.returncode == 0 and f"{g.name}/count/out:" in hz.stdout and "Hz" in hz.stdout


def test_shared_memory_pool_full_falls_back_to_the_socket():
    from common.runtime.shm import ShmWriter
    w = ShmWriter(1 << 20)
    held = [w.payload(b"h", b"x" * 400_000), w.payload(b"h", b"x" * 400_000)]
    assert all(h is not None for h in held) and bytes(held[0].to_bytes())[:2] == b"hx"
    assert w.payload(b"h", b"x" * 400_000) is None and w.failures == 1


def test_images_cross_processes_through_shared_memory_intact(run_graph):
    from common.runtime.messages import CameraImage
    from nodes.testpattern import pattern_image
    g = run_graph({"nodes": [
        {"id": "camera", "module": "testpattern", "params": {"rate_hz": 20, "width": 320, "height": 240}},
        {"id": "sink", "module": "framesink", "inputs": {"left": "camera/left", "right": "camera/right"}}]})
    msgs = g.collect("camera/right", n=3, timeout=10, expect=CameraImage)
    assert all(np.array_equal(m.to_bgr(), pattern_image(320, 240, 8)) for m in msgs)
    st = g.wait_stats("camera", lambda st: st.counters.get("out_shm", 0) > 0)
    assert st.counters.get("shm_pool_full", 0) == 0
    sink = g.wait_stats("sink", lambda st: st.counters.get("frames", 0) >= 5)
    assert sink.counters["decode_errors"] == 0 and sink.counters["handler_errors"] == 0


def test_handler_times_are_those_of_the_handlers_that_published():
    from common.runtime.process import Stats
    st = Stats()
    for ms, published in ((0.01, False), (12.0, True), (0.02, False), (0.03, False), (14.0, True)):
        st.proc(ms, published)
    _, _, p50, p99 = st.snapshot()
    assert 12.0 <= p50 <= 14.0 and p99 == 14.0      # the calibration-like messages left out
    sink = Stats()                                  # a node that never publishes: every handler
    sink.proc(3.0, False)
    assert sink.snapshot()[2] == 3.0


def test_a_replay_sends_its_prepared_raw_frames_intact_through_shared_memory(run_graph, tmp_path):
    """The replay copies its next frame into shared memory before sending it (``Node.prepare``);
    what arrives is the recorded image, stamped when sent."""
    from common.data.dataset import DatasetMeta, Frame
    from common.data.writer import DatasetWriter
    from common.geometry.camera import StereoRig
    from common.geometry.needle import NeedleModel
    from common.runtime.messages import CameraImage
    from common.sim.randomise import default_arm
    w, h = 320, 240
    meta = DatasetMeta((w, h), StereoRig.default(w, h), NeedleModel(), default_arm(), "test")
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 255, (h, w, 3), dtype=np.uint8) for _ in range(3)]
    with DatasetWriter(tmp_path / "ds", meta, image_format="png") as wr:
        for i, img in enumerate(images):
            paths = wr.write_images(i, {"left": img, "right": img[::-1].copy()})
            wr.append(Frame(index=i, stamp_ns=i * 10_000_000, left=paths["left"], right=paths["right"]))
    t0 = time.time_ns()
    g = run_graph({"nodes": [
        {"id": "replay", "module": "replay", "params": {"path": str(tmp_path / "ds"), "rate": 20, "loop": True,
                                                        "decode": True}},
        {"id": "sink", "module": "framesink", "inputs": {"left": "replay/left", "right": "replay/right"}}]})
    msgs = g.collect("replay/left", n=5, timeout=10, expect=CameraImage)
    t1 = time.time_ns()
    for m in msgs:
        assert np.array_equal(m.to_bgr(), images[m.seq % 3])
    # stamped when sent, not with the recorded stamps (0, 10, 20 ms): the pacing itself is
    # tested with a clock of its own (test_pacing.py), as a loaded machine may send late
    stamps = [m.stamp_ns for m in msgs]
    assert all(t0 < s < t1 for s in stamps) and stamps == sorted(set(stamps))
    st = g.wait_stats("replay", lambda st: st.counters.get("out_shm_prepared", 0) >= 4)
    assert st.counters.get("shm_pool_full", 0) == 0

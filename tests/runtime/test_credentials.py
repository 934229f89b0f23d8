"""Per-run credentials (common/runtime/credentials.py): a local graph no other process can steer.

Issue 32: on the default graph a foreign local process moved fused poses with fake
``PoseEstimate``s, and one handover query silenced a node for good. Now ``launch`` runs every
graph without ``zenoh.tls`` on mutual TLS with certificates made for the run (0600 files in a
0700 directory), with access control by identity; a handover needs the process's control token.
The intruder is ``common/robustness/intruder.py`` (a process without the credentials; as
another user, ``nobody``, when the tests run as root).
"""
import json
import os
import signal
import stat
import subprocess
import sys
import time

import pytest
import yaml
from graphtools import REPO, cli

from common.runtime import credentials
from common.runtime.graph import ctl_key, load_graph
from common.runtime.graph_checks import graph_warnings, validate_graph
from common.runtime.messages import PoseEstimate

NOBODY = 65534
GRAPH = {"nodes": [
    {"id": "epnp_joint", "module": "posesource", "params": {"rate_hz": 5, "count": 10}, "restart": "never"},
    {"id": "tick", "module": "counter", "params": {"rate_hz": 2}},
    {"id": "fusion", "module": "fusion", "params": {"k": 3}, "inputs": {"pose": "epnp_joint/pose"}},
]}


def _intrude(path, uid=None, duration=3.0) -> dict:
    args = [sys.executable, "-m", "common.robustness.intruder", str(path), "--duration", str(duration),
            "--keys", "epnp_joint/pose"] + ([] if uid is None else ["--uid", str(uid)])
    res = subprocess.run(args, cwd=REPO, env=dict(os.environ, PYTHONPATH=str(REPO)), capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr[-3000:]
    return json.loads(res.stdout.strip().splitlines()[-1])


def _poses_in(st) -> int:
    """Pose messages that reached the fusion (handled, or replaced while it was busy)."""
    return st.counters.get("in.pose", 0) + st.counters.get("dropped.pose", 0)


def _settled(g):
    """The fusion's stats once the estimator's 10 poses are out (the first may precede the
    fusion's subscription) and a stats period has passed."""
    g.wait_stats("fusion", lambda st: _poses_in(st) >= 5, timeout=60)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and any(r["state"] == "running" for r in g.status()["nodes"]
                                              if r["node"] == "epnp_joint"):
        time.sleep(0.2)
    time.sleep(1.5)
    return g.stats("fusion")


@pytest.fixture
def run_dir(tmp_path, monkeypatch):
    """Run credentials under the test's own folder (the launcher's subprocesses inherit it)."""
    d = tmp_path / "run"
    d.mkdir(mode=0o700)
    monkeypatch.setenv("NEEDLETRACK_RUN_DIR", str(d))
    return d


def test_validation_of_zenoh_open_and_the_warning():
    def errs(z):
        return validate_graph({"graph": "g", "zenoh": z, "nodes": GRAPH["nodes"]})
    assert errs({"open": True}) == [] and errs({"open": False}) == []
    assert errs({"open": "yes"}) == ["zenoh.open: expected true or false, got 'yes'"]
    tls = {"ca": "c.pem", "cert": "{id}.pem", "key": "{id}.key"}
    assert errs({"open": True, "listen": ["tls/127.0.0.1:7447"], "tls": tls}) == [
        "zenoh.open: true contradicts zenoh.tls (a TLS graph admits only its certificates): remove one"]
    e = errs({"listen": ["udp/127.0.0.1:7447"]})
    assert e and e[0].startswith("zenoh.listen[0]: 'udp/127.0.0.1:7447': the per-run credentials (the default) "
                                 "need tcp/ endpoints")
    assert errs({"listen": ["udp/127.0.0.1:7447"], "open": True}) == []
    g = load_graph({"graph": "g", "nodes": GRAPH["nodes"]})
    assert not g.zenoh.open and credentials.applies(g) and graph_warnings(g) == []
    w = graph_warnings(load_graph({"graph": "g", "zenoh": {"open": True}, "nodes": GRAPH["nodes"]}))
    assert len(w) == 1 and w[0].startswith("zenoh.open: true: the graph runs without credentials: any local process")
    assert load_graph({"graph": "g", "zenoh": {"open": True}, "nodes": GRAPH["nodes"]}).to_dict()["zenoh"]["open"]


def test_credentials_are_the_users_only_and_say_when_the_graph_is_not_running(run_dir):
    g = load_graph({"graph": "cred", "zenoh": {"listen": ["tcp/127.0.0.1:7999"]}, "nodes": GRAPH["nodes"]})
    with pytest.raises(credentials.CredentialsError) as exc:
        credentials.find(g)
    assert exc.value.errors[0].startswith("graph 'cred' at tcp/127.0.0.1:7999 is not running for this user: "
                                          f"no run credentials in {run_dir}/cred@127.0.0.1-7999")
    res = cli("ps", "-g", _dump(run_dir.parent / "g.yaml", g))
    assert res.returncode == 1 and "is not running for this user" in res.stderr, res.stderr
    sg, made = credentials.make(g)
    assert made and sg.zenoh.listen == ["tls/127.0.0.1:7999"] and sg.zenoh.tls is not None
    d = run_dir / "cred@127.0.0.1-7999"
    assert stat.S_IMODE(d.stat().st_mode) == 0o700
    keys = sorted(p.name for p in d.glob("*.key"))
    assert keys == ["epnp_joint.key", "fusion.key", "launcher.key", "tick.key"]      # no CA key
    assert all(stat.S_IMODE((d / k).stat().st_mode) == 0o600 for k in keys)
    assert credentials.make(g) == (credentials.find(g), False)      # its launcher runs: a second one joins
    assert credentials.find(g).zenoh.tls.cert == f"{d}/{{id}}.pem"
    os.chmod(d, 0o755)                                              # opened up: refused
    with pytest.raises(credentials.CredentialsError, match="is not this user's with mode 0700"):
        credentials.find(g)
    os.chmod(run_dir, 0o755)
    with pytest.raises(credentials.CredentialsError, match="is not a directory of uid"):
        credentials.base_dir()
    os.chmod(run_dir, 0o700)


def _dump(path, g):
    path.write_text(yaml.safe_dump({"graph": g.name, "zenoh": {"listen": list(g.zenoh.listen)},
                                    "nodes": [n.to_dict() for n in g.nodes]}))
    return path


def test_no_process_without_the_credentials_gets_a_fake_pose_or_a_handover_in(run_graph, run_dir):
    g = run_graph(GRAPH)
    assert "mutual TLS on per-run credentials" in g.log() and "WARNING" not in g.log()
    n = _poses_in(_settled(g))
    assert 5 <= n <= 10
    fusion_pid = g.pids()["fusion"]
    intruders = [_intrude(g.path)]                           # this user's process, without the files
    if os.getuid() == 0:
        intruders.append(_intrude(g.path, uid=NOBODY))       # another user's
        assert intruders[1]["uid"] == NOBODY and intruders[1]["credentials"].startswith("refused: [Errno 13]")
    else:
        print("not root: the other user's intruder (setuid nobody) is not run")
    for got in intruders:
        assert got["peers"] == {"tcp": 0, "tls": 0}, got
        assert got["poses_seen"] == 0 and got["poses_sent"] > 40
        assert got["handover_answers"] == [] and got["swap_answers"] == []
    time.sleep(2.5)                                          # a stats period after the last fake
    st = g.stats("fusion")
    assert _poses_in(st) == n and st.counters["state"] == "active" and st.pid == fusion_pid
    # the operator (the test's session: the launcher identity) gets in, so the count above could fail
    for seq in range(3):
        T = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.1], [0, 0, 0, 1]]
        g.put("epnp_joint/pose", PoseEstimate(100 + seq, time.time_ns(), "operator", __import__("numpy").array(T, float)))
        time.sleep(0.3)
    g.wait_stats("fusion", lambda s: _poses_in(s) == n + 3, timeout=20)


def test_a_handover_outside_a_swap_is_refused_and_a_retired_node_is_restarted(run_graph, run_dir):
    g = run_graph(GRAPH)
    _settled(g)
    pid = g.pids()["fusion"]
    answers = [json.loads(r.ok.payload.to_bytes()) for r in
               g.session.get(ctl_key(g.name, "fusion", pid, "handover"), timeout=5.0, payload=b"{}")
               if r.ok is not None]
    assert answers == [{"ok": False, "error": "handover refused: no valid control token"}]
    st = g.wait_stats("fusion", lambda s: s.counters.get("ctl_refused", 0) == 1, timeout=10)
    assert st.counters["state"] == "active" and st.pid == pid
    # a process of the same user can read the node's token from /proc: even then the launcher
    # notices the node that retired outside a swap and restarts it
    env = dict(kv.split("=", 1) for kv in open(f"/proc/{pid}/environ").read().split("\0") if "=" in kv)
    token = env["NEEDLETRACK_CTL_TOKEN"]
    got = [json.loads(r.ok.payload.to_bytes()) for r in
           g.session.get(ctl_key(g.name, "fusion", pid, "handover"), timeout=5.0,
                         payload=json.dumps({"token": token}).encode()) if r.ok is not None]
    assert got and got[0]["ok"] is True
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and g.pids().get("fusion") in (pid, None):
        time.sleep(0.2)
    new = g.pids()["fusion"]
    assert new not in (pid, None), g.log()[-3000:]
    assert f"fusion (pid {pid}) stopped publishing outside a swap (it reports 'retired'): restarting it" in g.log()
    g.wait_live(["fusion"])
    st = g.wait_stats("fusion", lambda s: s.pid == new, timeout=20)
    assert st.counters["state"] == "active"


def test_an_open_graph_lets_the_intruder_in_with_a_warning(run_graph, run_dir):
    """``zenoh.open: true`` (interop set-ups): what the default now refuses gets in."""
    g = run_graph({**GRAPH, "zenoh": {"open": True}})
    assert "[launcher] WARNING zenoh.open: true: the graph runs without credentials" in g.log()
    n = _poses_in(_settled(g))
    got = _intrude(g.path)
    assert got["peers"]["tcp"] >= 1 and got["poses_sent"] > 40
    g.wait_stats("fusion", lambda s: _poses_in(s) > n + 20, timeout=20)
    assert "[launcher] swap fusion: standby pid" in g.log()      # a stranger's swap is run, too
    assert len(got["handover_answers"]) >= 1                    # but a bare handover is refused (token)
    assert all(json.loads(a)["ok"] is False for a in got["handover_answers"])
    assert not list(run_dir.iterdir())                      # no credentials made


def test_cli_tools_use_the_runs_credentials_and_they_go_with_the_launcher(run_graph, run_dir):
    g = run_graph(GRAPH)
    d = credentials.run_dir(load_graph(g.path))
    assert d.is_dir() and (d / "owner.json").is_file()
    ps = g.cli("ps", "--json")
    assert ps.returncode == 0 and {r["node"] for r in json.loads(ps.stdout)} >= {"fusion", "tick"}, ps.stderr
    cmd = g.cli("cmd", "fusion", "reset")
    assert cmd.returncode == 0, cmd.stderr
    g.wait_stats("fusion", lambda s: s.counters.get("in.cmd", 0) == 1, timeout=20)
    assert g.stop() == 0
    assert not d.exists()
    res = cli("ps", "-g", g.path)
    assert res.returncode == 1 and "is not running for this user" in res.stderr


def test_credentials_of_a_killed_launcher_are_replaced_and_pruned(run_dir):
    g = load_graph({"graph": "kill", "zenoh": {"listen": ["tcp/127.0.0.1:7998"]}, "nodes": GRAPH["nodes"]})
    other = load_graph({"graph": "other", "zenoh": {"listen": ["tcp/127.0.0.1:7997"]}, "nodes": GRAPH["nodes"]})
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True).stdout.strip()
    for graph in (g, other):
        credentials.make(graph)
    for graph in (g, other):
        (credentials.run_dir(graph) / "owner.json").write_text(json.dumps({"pid": int(dead)}))   # launcher killed
    first = (credentials.run_dir(g) / "ca.pem").read_bytes()
    sg, made = credentials.make(g)
    assert made and (credentials.run_dir(g) / "ca.pem").read_bytes() != first
    assert not credentials.run_dir(other).exists()                          # the other dead run: pruned
    credentials.remove(sg)
    assert not credentials.run_dir(g).exists()

"""zenoh.tls: validation with places, the warning for a listen beyond loopback without TLS, the
session configuration, the certificates of ``needletrack certs``, and a TLS graph on loopback
(swap, commands) that refuses what an identity may not do. The two-host test is
tests/runtime/test_multihost_tls.py."""
import json
import secrets
import subprocess
import time

import pytest
import yaml
from graphtools import cli
from netns_probe import intruder_config

from common.runtime.certs import make_graph_certs
from common.runtime.graph import GraphError, launcher_key, load_graph
from common.runtime.graph_checks import graph_warnings, validate_graph
from common.runtime.zenoh_session import access_control, zenoh_config
from common.runtime.messages import Command, encode

pytestmark = pytest.mark.graph

NODES = [{"id": "count", "module": "counter", "params": {"rate_hz": 25}},
         {"id": "det", "module": "tagger", "params": {"tag": "A"}, "inputs": {"in": "count/out"}}]
TLS = {"ca": "certs/ca.pem", "cert": "certs/{id}.pem", "key": "certs/{id}.key"}


def _errors(zenoh, nodes=NODES):
    return validate_graph({"graph": "g", "zenoh": zenoh, "nodes": nodes})


def test_a_tls_endpoint_without_certificates_is_an_error_at_its_place():
    errs = _errors({"listen": ["tls/10.0.0.1:7447"]})
    assert len(errs) == 1 and errs[0].startswith("zenoh.listen[0]: 'tls/10.0.0.1:7447' is a TLS endpoint: "
                                                 "configure zenoh.tls {ca, cert, key}")
    errs = _errors({"listen": ["tls/10.0.0.1:7447"], "connect": ["tcp/10.0.0.2:7447"], "tls": TLS})
    assert errs == ["zenoh.connect[0]: 'tcp/10.0.0.2:7447': with zenoh.tls every endpoint must be tls/ "
                    "(another protocol would bypass TLS and access control)"]
    errs = _errors({"listen": ["tls/127.0.0.1:7447"], "tls": {"ca": "ca.pem", "cert": "node.pem", "vrfy": 1}})
    assert any(e.startswith("zenoh.tls.cert: must contain '{id}'") for e in errs)
    assert "zenoh.tls.key: missing (a PEM file path, with {id})" in errs
    assert any(e.startswith("zenoh.tls.vrfy: unknown key") for e in errs)
    errs = _errors({"listen": ["tls/127.0.0.1:7447"], "tls": TLS}, NODES + [{"id": "launcher", "module": "counter"}])
    assert errs == ["nodes[2].id: 'launcher' is the launcher's TLS identity (zenoh.tls): rename the node"]
    assert _errors({"listen": ["tls/127.0.0.1:7447"], "tls": TLS}) == []


def test_listening_beyond_loopback_without_tls_is_warned_about(tmp_path):
    def warns(listen, tls=None, open_=True):
        z = {"listen": listen, **({"tls": tls} if tls else {"open": open_})}
        return graph_warnings(load_graph({"graph": "g", "zenoh": z, "nodes": NODES}))[int(open_ and not tls):]
    assert warns(["tcp/127.0.0.1:7447", "tcp/[::1]:7447", "tcp/localhost:7447"]) == []
    assert warns(["tls/0.0.0.0:7447"], TLS) == []
    assert warns(["tcp/0.0.0.0:7447"], open_=False) == []      # per-run credentials: TLS on every link
    w = warns(["tcp/127.0.0.1:7447", "tcp/0.0.0.0:7447"])
    assert len(w) == 1 and w[0].startswith("zenoh.listen[1]: 'tcp/0.0.0.0:7447' listens beyond this host without TLS")
    path = tmp_path / "open.yaml"
    path.write_text(yaml.safe_dump({"graph": "g", "zenoh": {"listen": ["tcp/192.168.1.5:7447"], "open": True},
                                    "nodes": NODES}))
    res = cli("validate", path)
    assert res.returncode == 0 and "WARNING zenoh.listen[0]: 'tcp/192.168.1.5:7447' listens beyond" in res.stderr


def test_certificates_and_session_configuration(tmp_path):
    path = tmp_path / "g.yaml"
    path.write_text(yaml.safe_dump({"graph": "g", "zenoh": {"listen": ["tls/127.0.0.1:7447"], "tls": TLS},
                                    "nodes": NODES}))
    g = load_graph(path)
    assert g.zenoh.tls.ca == str(tmp_path / "certs" / "ca.pem")          # relative to the graph file
    with pytest.raises(GraphError) as exc:
        zenoh_config(g, identity="det")
    assert f"zenoh.tls.cert: no file {tmp_path}/certs/det.pem (identity 'det')" in str(exc.value)
    res = cli("certs", path)
    assert res.returncode == 0, res.stderr
    certs = tmp_path / "certs"
    for ident in ("launcher", "count", "det"):
        subject = subprocess.run(["openssl", "x509", "-in", certs / f"{ident}.pem", "-noout", "-subject"],
                                 capture_output=True, text=True).stdout
        assert f"CN = g:{ident}" in subject
        ok = subprocess.run(["openssl", "verify", "-CAfile", certs / "ca.pem", certs / f"{ident}.pem"],
                            capture_output=True, text=True)
        assert ok.returncode == 0, ok.stdout + ok.stderr
        assert (certs / f"{ident}.key").stat().st_mode & 0o077 == 0
    c = zenoh_config(g, role="node", identity="det")
    tls = json.loads(c.get_json("transport/link/tls"))
    assert tls["enable_mtls"] is True and tls["connect_certificate"] == str(certs / "det.pem")
    assert tls["verify_name_on_connect"] is False
    assert tls["listen_private_key"] == str(certs / "det.key")
    assert json.loads(c.get_json("listen/endpoints")) == ["tls/127.0.0.1:0"]
    acl = json.loads(c.get_json("access_control"))
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    rules = {r["id"]: r for r in access_control(g)["rules"]}
    assert rules["node:det:publish"]["key_exprs"] == ["g/det/out", "g/@stats/det"]
    assert "put" not in rules["members-subscribe"]["messages"]


def test_a_tls_graph_swaps_and_takes_commands_only_from_the_launcher_identity(run_graph, tmp_path):
    import zenoh
    name = f"tls{secrets.token_hex(3)}"
    certs = tmp_path / "certs"
    tls = {k: str(certs / v.split("/")[-1]) for k, v in TLS.items()}
    tls["verify_name"] = True                          # the certificates name 127.0.0.1
    data = {"graph": name, "zenoh": {"listen": ["tls/127.0.0.1:7447"], "tls": tls}, "nodes": NODES}
    make_graph_certs(load_graph(data))
    g = run_graph(data)                                # the test's own session: the launcher identity
    sub = g.subscribe("det/out")
    sub.wait(5, 20)
    intruders = [zenoh.open(zenoh_config(g.graph, role="node", identity="count")),   # a member, not det
                 zenoh.open(intruder_config(g.graph))]                               # no certificate
    try:
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and not list(intruders[0].info.peers_zid()):
            time.sleep(0.05)
        time.sleep(1.0)
        assert list(intruders[0].info.peers_zid()) and not list(intruders[1].info.peers_zid())
        for s in intruders:
            for _ in range(10):
                s.put(g.key("det/out"), b"forged")
            s.put(g.key("det/cmd"), encode(Command("hello", None)))
            assert [r for r in s.get(launcher_key(name, "swap"), timeout=3.0,
                                     payload=json.dumps({"node": "det", "params": {"tag": "X"}}).encode())] == []
    finally:
        for s in intruders:
            s.close()
    g.command("det", "hello")
    g.wait_stats("det", lambda st: st.counters.get("in.cmd", 0) >= 1, timeout=20)
    time.sleep(1.5)
    assert g.stats("det").counters.get("in.cmd") == 1          # the launcher's, none of the intruders'
    assert sub.undecodable == [] and {m.detector for m in sub.messages} == {"A"}
    res = g.swap("det", tag="B")                               # handover and takeover under access control
    assert res.returncode == 0 and "swapped det" in res.stdout, res.stdout + res.stderr
    sub.wait(5, 20, where=lambda m: m.detector == "B")
    assert "[launcher] WARNING" not in g.log() and "mutual TLS" in g.log()

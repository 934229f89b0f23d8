"""dataflow.yaml: loading, validation (every error with its place), keys, Zenoh settings, CLI."""
import json

import pytest
from graphtools import REPO, cli

import common.runtime.graph as graph_mod
from common import cli as cli_mod
from common.runtime.graph import GraphError, load_graph, module_info, parse_param
from common.runtime.graph_checks import validate_graph
from common.runtime.zenoh_session import zenoh_config

GOOD = {"graph": "g", "nodes": [
    {"id": "count", "module": "counter", "params": {"rate_hz": 5}},
    {"id": "relay", "module": "relay", "inputs": {"in": "count/out"}, "restart": "always",
     "env": {"OMP_NUM_THREADS": 1}},
]}


def test_the_repository_graph_is_valid():
    g = load_graph(REPO / "dataflow.yaml")
    assert g.name == "needletrack" and g.ids()
    assert g.zenoh.listen == ["tcp/127.0.0.1:7447"]


def test_a_valid_graph_loads_with_defaults():
    g = load_graph(GOOD)
    relay = g.node("relay")
    assert relay.outputs == ["out"]                  # from the module, read without importing it
    assert relay.env == {"OMP_NUM_THREADS": "1"} and relay.restart == "always"
    assert g.node("count").restart == "on-failure"
    assert g.zenoh.mode == "peer" and g.zenoh.listen == ["tcp/127.0.0.1:7447"]
    assert g.input_key(relay, "in") == "g/count/out"
    assert g.resolve_key("relay/out") == "g/relay/out" and g.resolve_key("g/relay/out") == "g/relay/out"
    with pytest.raises(KeyError, match="no node 'nope'"):
        g.node("nope")


def test_every_error_is_reported_at_once_with_its_place():
    bad = {"graph": "a b", "zenoh": {"mode": "mesh", "listen": ["127.0.0.1:7447"], "extra": 1},
           "colour": "red",
           "nodes": [
               {"id": "cam", "module": "counter", "restart": "sometimes", "params": [1]},
               {"id": "det", "module": "relay", "inputs": {"in": "detektor/out", "bogus": "cam/out"}},
               {"id": "det", "module": "relay", "inputs": {"in": "cam/lft"}},
               {"id": "x", "module": "does_not_exist"},
               {"id": "y", "module": "counter", "command": ["echo"]},
               {"id": "z", "command": "echo hi", "env": {"1BAD": "v", "OK": [1]}},
               {"id": "w", "module": "counter", "outputs": ["out", "out", "nope"]},
               "not a map",
           ]}
    errs = validate_graph(bad)
    expected = [
        "colour: unknown key",
        "graph: must be a name",
        "zenoh.extra: unknown key",
        "zenoh.mode: must be one of peer, client, router; got 'mesh'",
        "zenoh.listen[0]: not an endpoint",
        "nodes[0].restart: must be one of never, on-failure, always; got 'sometimes'",
        "nodes[0].params: expected a map, got list",
        "nodes[1].inputs.in: no node 'detektor'",
        "nodes[1].inputs.bogus: module 'relay' has no input 'bogus' (inputs: in)",
        "nodes[2].id: duplicate id 'det' (also nodes[1])",
        "nodes[2].inputs.in: node 'cam' has no output 'lft' (outputs: out)",
        "nodes[3].module: unknown module 'does_not_exist': no file nodes/does_not_exist.py",
        "nodes[4]: needs exactly one of 'module' (a module of nodes/) or 'command'",
        "nodes[5].command: expected a non-empty list of strings",
        "nodes[5].env.1BAD: not a valid environment variable name",
        "nodes[5].env.OK: expected a scalar, got list",
        "nodes[6].outputs[1]: duplicate output 'out'",
        "nodes[6].outputs[2]: module 'counter' has no output 'nope' (outputs: out)",
        "nodes[7]: expected a map with id and module, got string",
    ]
    for e in expected:
        assert any(x.startswith(e) for x in errs), f"missing {e!r} in:\n" + "\n".join(errs)
    assert len(errs) == len(expected), "\n".join(errs)
    with pytest.raises(GraphError) as exc:
        load_graph(bad)
    assert exc.value.errors == errs and f"{len(errs)} error(s)" in str(exc.value)


def test_structural_errors():
    assert validate_graph([1, 2])[0].startswith("top level: expected a map")
    assert validate_graph({"graph": "g"}) == ["nodes: missing (a list of nodes)"]
    assert validate_graph({"graph": "g", "nodes": []}) == ["nodes: empty"]
    assert validate_graph({"nodes": {"a": 1}}) == ["graph: missing (the key prefix of the graph, e.g. 'needletrack')",
                                                   "nodes: expected a list, got map"]


def test_yaml_syntax_errors_name_the_line(tmp_path):
    p = tmp_path / "broken.yaml"
    p.write_text("graph: g\nnodes:\n  - id: a\n    module: [counter\n")
    with pytest.raises(GraphError) as exc:
        load_graph(p)
    assert exc.value.errors[0].startswith("line ") and "YAML syntax error" in exc.value.errors[0]
    assert str(p) in str(exc.value)
    with pytest.raises(GraphError, match="no such file"):
        load_graph(tmp_path / "absent.yaml")


def test_modules_are_checked_without_importing_them(tmp_path, monkeypatch):
    (tmp_path / "nonode.py").write_text("import torch_that_does_not_exist\nclass A: pass\n")
    (tmp_path / "broken.py").write_text("def f(:\n")
    (tmp_path / "dyn.py").write_text("INS = {'a': None}\nclass N:\n    INPUTS = INS\n    OUTPUTS = ('o',)\nNODE = N\n")
    monkeypatch.setattr(graph_mod, "NODES_DIR", tmp_path)
    errs = validate_graph({"graph": "g", "nodes": [
        {"id": "a", "module": "nonode"}, {"id": "b", "module": "broken"},
        {"id": "c", "module": "dyn", "inputs": {"anything": "c/o"}}]})
    assert errs == ["nodes[0].module: nodes/nonode.py defines no NODE",
                    "nodes[1].module: nodes/broken.py has a syntax error at line 1: invalid syntax"]
    info = module_info("dyn")
    assert info["inputs"] is None and info["outputs"] == ["o"]       # non-literal INPUTS: not checked
    assert module_info("absent") is None


def test_parse_param_reads_yaml_scalars():
    assert parse_param("backend=learned") == ("backend", "learned")
    assert parse_param("noise_px=1.5") == ("noise_px", 1.5)
    assert parse_param("flags=[1, 2]") == ("flags", [1, 2])
    assert parse_param("empty=") == ("empty", "")
    for bad in ("novalue", "=3"):
        with pytest.raises(ValueError):
            parse_param(bad)


def test_zenoh_settings_are_hermetic():
    g = load_graph({**GOOD, "zenoh": {"listen": ["tcp/127.0.0.1:17447"]}})
    hub = json.loads(zenoh_config(g.zenoh, role="hub").get_json("listen"))
    node_cfg = zenoh_config(g.zenoh, role="node")
    assert hub["endpoints"] == ["tcp/127.0.0.1:17447"]
    assert json.loads(node_cfg.get_json("listen"))["endpoints"] == ["tcp/127.0.0.1:0"]
    assert json.loads(node_cfg.get_json("connect"))["endpoints"] == ["tcp/127.0.0.1:17447"]
    assert json.loads(node_cfg.get_json("scouting/multicast/enabled")) is False


def test_the_cli_dispatches_lazily(monkeypatch, capsys):
    monkeypatch.setitem(cli_mod.COMMANDS, "later", ("common.not_written_yet:main", "a command still to come"))
    assert cli_mod.main(["later"]) == 1
    assert "common.not_written_yet is not available yet" in capsys.readouterr().err
    assert cli_mod.main(["frobnicate"]) == 2
    assert cli_mod.main([]) == 2 and "later" in capsys.readouterr().out
    assert cli_mod.bench_main(["nope"]) == 2
    calls = []
    monkeypatch.setitem(cli_mod.BENCHES, "graph", ("common.cli:_record", ""))
    monkeypatch.setattr(cli_mod, "_record", lambda argv: calls.append(argv) or 0, raising=False)
    assert cli_mod.main(["bench", "--dataset", "D"]) == 0 and cli_mod.main(["bench"]) == 0
    assert calls == [["--dataset", "D"], []]
    for name in ("dataset", "train", "eval", "launch", "ps", "echo", "hz", "swap", "validate", "bench"):
        assert name in cli_mod.COMMANDS
    for name in ("transport", "sim", "detector", "graph"):
        assert name in cli_mod.BENCHES


def test_validate_command(tmp_path):
    ok = cli("validate", REPO / "dataflow.yaml")
    assert ok.returncode == 0 and "ok: graph 'needletrack'" in ok.stdout
    bad = tmp_path / "bad.yaml"
    bad.write_text("graph: g\nnodes:\n  - {id: a, module: counter}\n  - {id: b, module: relay, inputs: {in: a/nope}}\n")
    res = cli("validate", bad)
    assert res.returncode == 2
    assert "nodes[1].inputs.in: node 'a' has no output 'nope' (outputs: out)" in res.stderr


def test_validate_and_launch_check_every_nodes_typed_params(tmp_path):
    """A misspelt param or a value of the wrong type is reported with its place (exit 2) by
    validate and by launch, before any node starts (no node crash-loops on a bad param)."""
    bad = tmp_path / "params.yaml"
    bad.write_text("graph: typed\nnodes:\n"
                   "  - {id: a, module: counter, params: {rate_hz: 5, cont: 3}}\n"
                   "  - {id: b, module: relay, params: {work_ms: fast}, inputs: {in: a/out}}\n"
                   "  - {id: d, module: detector, params: {backend: learned, threads: five}}\n")
    for command in ("validate", "launch"):
        res = cli(command, bad, timeout=60)
        assert res.returncode == 2, (command, res.stdout, res.stderr)
        for text in ("nodes[0].params.cont: unknown param (did you mean 'count'?)",
                     "nodes[1].params.work_ms: expected number, got 'fast'",
                     "nodes[2].params.threads: expected int, got 'five'"):
            assert text in res.stderr, (command, res.stderr)
    assert "up (pid" not in res.stdout + res.stderr          # launch started no node


def test_a_node_that_cannot_run_as_configured_stops_the_graph_and_launch_fails(tmp_path):
    """Params of the right types that still cannot work (a dataset folder that is not there):
    the node exits 2, is not restarted, and launch says so and exits non-zero."""
    g = tmp_path / "g.yaml"
    g.write_text("graph: exit2\nnodes:\n"
                 f"  - {{id: camera, module: replay, restart: always, params: {{path: {tmp_path / 'missing'}}}}}\n"
                 "  - {id: count, module: counter, params: {rate_hz: 5}}\n")
    res = cli("launch", g, timeout=120)
    assert res.returncode != 0, res.stdout + res.stderr
    out = res.stdout + res.stderr
    assert "status 2 = bad configuration" in out and "camera cannot run as configured: stopping the graph" in out
    assert "restart #" not in out


def test_the_params_constraints_are_seen_by_validate_before_any_node_runs():
    """What a node's setup once checked by hand is a constraint of its params' fields: the
    params' check of validate and launch reports it, placed, with no node started."""
    from common.runtime.graph import graph_from_dict
    from common.runtime.node import graph_param_errors
    doc = {"graph": "constrained", "nodes": [
        {"id": "a", "module": "counter", "params": {"rate_hz": 0}},
        {"id": "v", "module": "viewer", "params": {"width": 8, "max_connections": 0, "final": "best"}},
        {"id": "t", "module": "tracker", "params": {"max_wait": 0, "replay": -1}},
        {"id": "e", "module": "epnp", "params": {"min_sigma_px": -0.5}},
        {"id": "o", "module": "ros2_out", "params": {"topic": "needle_pose"}},
        {"id": "b", "module": "rosbag", "params": {"path": "x.bag", "preset": "davinci"}},
        {"id": "f", "module": "fusion", "params": {"k": 0, "max_dist_mm": -1}}]}
    errs = "\n".join(graph_param_errors(graph_from_dict(doc)))
    for text in ("nodes[0].params.rate_hz: must be a positive number, got 0",
                 "nodes[1].params.width: must be at least 16, got 8",
                 "nodes[1].params.max_connections: must be at least 1, got 0",
                 "nodes[1].params.final: expected 'pnp_average' or",
                 "nodes[2].params.max_wait: must be at least 1, got 0",
                 "nodes[2].params.replay: must be at least 0, got -1",
                 "nodes[3].params.min_sigma_px: must be a positive number, got -0.5",
                 "nodes[4].params.topic: must be an absolute ROS name, got 'needle_pose'",
                 "nodes[5].params.preset: expected 'ambf' or 'dvrk' or null, got 'davinci'",
                 "nodes[6].params.k: must be at least 1, got 0",
                 "nodes[6].params.max_dist_mm: must be a positive number, got -1"):
        assert text in errs, (text, errs)


@pytest.mark.parametrize("path", sorted((REPO / "graphs").glob("*.yaml")), ids=lambda p: p.name)
def test_every_shipped_graph_validates(path):
    ok = cli("validate", path)
    assert ok.returncode == 0, ok.stderr

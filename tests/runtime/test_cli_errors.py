"""The command line on bad paths and bad arguments: a clear error naming what and where, a
non-zero exit, no traceback, and no user file removed: ``eval --rrd/--out``, ``certs --out``,
``validate`` on a binary file, ``cmd``/``swap`` with a deeply nested argument, ``cmd`` to a node
that does not exist or is not running."""
import json
import os
import subprocess
import sys

import pytest
from graphtools import REPO, cli, free_port

from common.runtime.graph import parse_param
from common.runtime.limits import MAX_YAML_DEPTH, InputLimitError, load_yaml
from common.viewer.recording import rrd_target_problem

DEEP = "[" * 5000 + "]" * 5000


def _no_traceback(p: subprocess.CompletedProcess) -> None:
    assert "Traceback" not in p.stdout + p.stderr, p.stdout + p.stderr


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    from common.cli import dataset_main
    ds = tmp_path_factory.mktemp("cli") / "ds"
    assert dataset_main(["generate", "--out", str(ds), "--sequences", "1", "--steps", "2", "--width", "320",
                         "--height", "180", "--seed", "3", "--randomise", "none", "--jobs", "1", "--quiet"]) == 0
    return ds


@pytest.mark.graph
def test_eval_rrd_never_removes_a_file_that_is_not_a_recording(tiny_dataset, tmp_path):
    notes = tmp_path / "notes.txt"
    notes.write_text("the surgeon's notes\n")
    folder = tmp_path / "folder.rrd"
    folder.mkdir()
    link = tmp_path / "link.rrd"
    link.symlink_to(notes)
    for target, says in ((notes, "is not a Rerun recording"), (folder, "is not a regular file"),
                         (link, "is a symbolic link"), (tmp_path / "nowhere" / "x.rrd", "does not exist")):
        p = cli("eval", "--dataset", tiny_dataset, "--detector", "oracle", "--out", tmp_path / "out",
                "--quiet", "--rrd", target, timeout=120)
        assert p.returncode == 2 and says in p.stderr and str(target) in p.stderr, p.stderr
        _no_traceback(p)
    assert notes.read_text() == "the surgeon's notes\n" and folder.is_dir() and link.is_symlink()
    assert not (tmp_path / "out").exists()          # refused before anything was made


def test_rrd_target_problem_lets_a_recording_be_replaced(tmp_path):
    rrd = tmp_path / "old.rrd"
    rrd.write_bytes(b"RRF2" + bytes(60))
    assert rrd_target_problem(rrd) is None and rrd_target_problem(tmp_path / "new.rrd") is None
    empty = tmp_path / "empty.rrd"
    empty.write_bytes(b"")
    assert "not a Rerun recording" in rrd_target_problem(empty)


def test_eval_out_on_a_file_is_a_clear_error(tiny_dataset, tmp_path):
    f = tmp_path / "results"
    f.write_text("keep me\n")
    for out, says in ((f, "exists and is not a folder"), (f / "sub", "cannot write")):
        p = cli("eval", "--dataset", tiny_dataset, "--detector", "oracle", "--out", out, "--quiet", timeout=120)
        assert p.returncode == 2 and says in p.stderr and str(f) in p.stderr, p.stderr
        _no_traceback(p)
    assert f.read_text() == "keep me\n"


def test_certs_out_on_a_file_or_a_read_only_folder_is_a_clear_error(tmp_path):
    graph = REPO / "dataflow.yaml"
    f = tmp_path / "afile"
    f.write_text("x")
    p = cli("certs", graph, "--out", f)
    assert p.returncode == 2 and f"--out {f} exists and is not a folder" in p.stderr, p.stderr
    p = cli("certs", graph, "--out", f / "sub")
    assert p.returncode == 1 and f"cannot write {f / 'sub'}" in p.stderr, p.stderr
    _no_traceback(p)
    # a read-only file system, mounted in a mount namespace of the test's own
    ro = tmp_path / "ro"
    ro.mkdir()
    env = dict(os.environ, PYTHONPATH=str(REPO))
    script = (f"mount -t tmpfs -o ro tmpfs {ro} && {sys.executable} -m common.cli certs {graph} --out {ro}/certs")
    p = subprocess.run(["unshare", "-rm", "sh", "-c", script], capture_output=True, text=True, env=env,
                       cwd=REPO, timeout=120)
    assert p.returncode == 1 and f"cannot write {ro}/certs: Read-only file system" in p.stderr, p.stderr
    _no_traceback(p)


def test_validate_a_binary_file_names_it_and_the_byte(tmp_path):
    binary = tmp_path / "graph.yaml"
    binary.write_bytes(b"nodes: \xff\xfe\x00\x01" + os.urandom(200))
    nul = tmp_path / "nul.yaml"
    nul.write_bytes(b"graph: a\x00b\n")
    p = cli("validate", binary, nul)
    assert p.returncode == 2, p.stderr
    assert f"{binary}" in p.stderr and "not a YAML text file: byte 7 is not UTF-8" in p.stderr, p.stderr
    assert f"{nul}" in p.stderr and "not a YAML text file: byte 8 is NUL" in p.stderr, p.stderr
    _no_traceback(p)


def test_a_deeply_nested_argument_is_refused_with_its_place(tmp_path):
    with pytest.raises(InputLimitError, match=f"nested deeper than {MAX_YAML_DEPTH}"):
        parse_param("x=" + DEEP)
    with pytest.raises(InputLimitError, match="line 3"):
        load_yaml("a: 1\nb:\n" + "  " + "[" * 200 + "]" * 200, "here")
    assert parse_param("x=" + "[" * 50 + "]" * 50)[1] is not None         # within the limit
    assert parse_param("x=[1, {a: 2}]") == ("x", [1, {"a": 2}]) and parse_param("x=a: b: c") == ("x", "a: b: c")
    for args in (("cmd", "camera", "place_needle", "T=" + DEEP), ("swap", "camera", "--param", "x=" + DEEP)):
        p = cli(*args)
        assert p.returncode == 2 and "the value of" in p.stderr and "nested deeper than" in p.stderr, p.stderr
        _no_traceback(p)


def _graph_file(tmp_path):
    g = tmp_path / "g.yaml"
    g.write_text(json.dumps({"graph": f"clierr{os.getpid()}", "zenoh": {"listen": [f"tcp/127.0.0.1:{free_port()}"]},
                             "nodes": [{"id": "count", "module": "counter", "params": {"rate_hz": 5}}]}))
    return g


def test_cmd_to_a_node_the_graph_does_not_have_suggests_one(tmp_path):
    p = cli("cmd", "-g", _graph_file(tmp_path), "cuont", "reset")
    assert p.returncode == 2 and "has no node 'cuont' (did you mean 'count'?)" in p.stderr, p.stderr
    assert "sent" not in p.stdout


@pytest.mark.slow
def test_cmd_to_a_graph_that_is_not_running_says_no_node_answered(tmp_path):
    p = cli("cmd", "-g", _graph_file(tmp_path), "count", "reset")
    # on the default per-run credentials a graph that is not running has none: said before anything is sent
    assert p.returncode == 1 and ("no node answered" in p.stderr and "nothing sent" in p.stderr
                                  or "is not running for this user: no run credentials" in p.stderr), p.stderr
    assert "sent reset" not in p.stdout


def test_cmd_to_a_running_node_is_sent(run_graph):
    g = run_graph({"nodes": [{"id": "count", "module": "counter", "params": {"rate_hz": 5}}]})
    p = g.cli("cmd", "count", "reset")
    assert p.returncode == 0 and "sent reset" in p.stdout, p.stdout + p.stderr

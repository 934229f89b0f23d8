"""The README's front door shows what runs: its graph drawing is ``dataflow.yaml``'s nodes and
wires, its sample monitor line is what the monitor prints for that graph, and its screenshot is
made by a command that exists."""
import re
from pathlib import Path

import pytest

from common.methods import POSE_METHODS, final_method
from common.runtime.graph import load_graph

REPO = Path(__file__).resolve().parents[2]
NOT_DRAWN = {"calib"}      # "most nodes also take camera/calib, not drawn"
NODE = re.compile(r'^\s*(\w+)\["([^"]*)"\]\s*$')
EDGE = re.compile(r'^\s*(\w+(?:\s*&\s*\w+)*)\s*-->\|("?)([^|"]+)\2\|\s*(\w+(?:\s*&\s*\w+)*)\s*$')


def mermaid_wires(text: str) -> tuple[set, set]:
    """(node ids, wires (source id, output, destination id, input or None)) of the first mermaid
    block of ``text``: a node's id is the first line of its label (else its mermaid name); an
    arrow's label lists ``output`` or ``output: input`` items. Raises ValueError on a line it
    cannot read."""
    block = re.search(r"```mermaid\n(.*?)```", text, re.S)
    if block is None:
        raise ValueError("no mermaid block")
    names, edges = {}, []
    for line in block.group(1).splitlines()[1:]:
        if not line.strip():
            continue
        if m := NODE.match(line):
            names[m[1]] = m[2].split("<br/>")[0].strip()
        elif m := EDGE.match(line):
            edges.append(([s.strip() for s in m[1].split("&")], m[3], [d.strip() for d in m[4].split("&")]))
        else:
            raise ValueError(f"README graph: cannot read {line.strip()!r}")
    wires = set()
    for sources, label, dests in edges:
        for item in label.split(","):
            out, _, inp = (x.strip() for x in item.partition(":"))
            wires |= {(names.get(s, s), out, names.get(d, d), inp or None) for s in sources for d in dests}
    ids = set(names.values()) | {n for s, _, d, _ in wires for n in (s, d)}
    return ids, wires


def graph_wires(graph) -> tuple[set, set]:
    """(node ids, wires (source id, output, destination id, input)) of a loaded graph, less the
    inputs the README does not draw."""
    wires = set()
    for n in graph.nodes:
        for inp, src in (n.inputs or {}).items():
            node, _, out = src.partition("/")
            if out not in NOT_DRAWN:
                wires.add((node, out, n.id, inp))
    return set(graph.ids()), wires


def test_the_readmes_graph_is_dataflow_yaml():
    ids, drawn = mermaid_wires((REPO / "README.md").read_text())
    want_ids, want = graph_wires(load_graph(REPO / "dataflow.yaml"))
    assert ids == want_ids, f"nodes drawn but not run: {ids - want_ids}; run but not drawn: {want_ids - ids}"
    # an arrow labelled ``output: input`` must name the input it feeds; ``output`` alone fits any
    named = {w for w in drawn if w[3] is not None}
    assert named <= want, f"drawn with an input that is not so wired: {named - want}"
    bare = {w[:3] for w in drawn}
    assert bare == {w[:3] for w in want}, (f"drawn but not wired: {bare - {w[:3] for w in want}}; "
                                           f"wired but not drawn: {({w[:3] for w in want}) - bare}")


def test_the_graph_check_sees_a_missing_node_and_a_wrong_wire():
    text = (REPO / "README.md").read_text()
    want_ids, want = graph_wires(load_graph(REPO / "dataflow.yaml"))
    no_tracker = "\n".join(line for line in text.splitlines() if "tracker" not in line)
    ids, drawn = mermaid_wires(no_tracker)
    assert "tracker" not in ids and ids != want_ids
    ids, drawn = mermaid_wires(text.replace('-->|"pose: refined"| monitor', '-->|"pose: tracked"| monitor'))
    assert not {w for w in drawn if w[3]} <= want
    with pytest.raises(ValueError, match="cannot read"):
        mermaid_wires("```mermaid\nflowchart LR\n  a --> b\n```\n")


def test_the_readmes_monitor_line_is_what_the_monitor_prints_for_the_default_graph():
    from nodes.monitor import format_lines
    readme = (REPO / "README.md").read_text()
    sample = re.search(r"^seq +\d+ (\d+)/(\d+) (\w+) +t=\[.*\]mm r=\[.*\]deg err [\d.]+mm [\d.]+deg$", readme, re.M)
    assert sample, "no sample monitor line in the README"
    monitor = next(n for n in load_graph(REPO / "dataflow.yaml").nodes if n.module == "monitor")
    methods = [m for m in POSE_METHODS if m in (monitor.inputs or {})]
    assert (int(sample[1]), int(sample[2]), sample[3]) == (len(methods), len(methods), final_method(methods))
    assert format_lines(1, {}, None, methods)[0].split()[2:4] == ["0/%d" % len(methods), final_method(methods)]


def test_the_readmes_screenshot_is_made_by_a_command_that_exists():
    from common.cli import COMMANDS
    readme = (REPO / "README.md").read_text()
    m = re.search(r"`needletrack (\w+) --out docs/launch\.png`", readme)
    assert m and m[1] in COMMANDS and "docs/launch.png" in readme
    assert (REPO / "docs" / "launch.png").stat().st_size > 50_000

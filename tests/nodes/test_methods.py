"""The pose-method registry (common/methods.py) is the one list of methods."""
import ast
from pathlib import Path

from common.methods import (
    BY_NAME,
    FINAL_ORDER,
    MULTIVIEW_METHODS,
    POSE_METHODS,
    POSE_OUTPUTS,
    REGISTRY,
    final_method,
    in_final_order,
    last_stage,
)
from nodes.evaluator import EvaluatorNode
from nodes.monitor import MonitorNode

REPO = Path(__file__).resolve().parents[2]


def test_the_registry_is_consistent():
    assert len(set(POSE_METHODS)) == len(POSE_METHODS) == len(REGISTRY)
    assert sorted(FINAL_ORDER) == sorted(POSE_METHODS)
    for m in REGISTRY:
        assert m.colour.startswith("#") and len(m.colour) == 7
        if m.fuses is not None:           # a multi-view method fuses a single-frame one
            assert m.fuses in BY_NAME and not BY_NAME[m.fuses].multiview
    assert len({m.output for m in REGISTRY}) == len(REGISTRY)


def test_nodes_that_take_every_method_take_the_registry():
    for node in (EvaluatorNode, MonitorNode):
        assert set(POSE_METHODS) <= set(node.INPUTS)


def test_the_final_method_and_the_last_stage():
    assert final_method([]) is None
    assert final_method(["pnp_average", "multiview"]) == "multiview"
    assert final_method(["pnp_joint", "refined"]) == "refined"
    assert final_method(["multiview_refined", "refined", "tracked"]) == "tracked"
    assert final_method(["someone_elses"]) == "someone_elses"
    assert in_final_order(["x", "triangulation", "refined"]) == ["refined", "triangulation", "x"]
    assert last_stage(["refined", "multiview", "pnp_joint"]) == "multiview"
    assert last_stage(["refined", "pnp_joint"]) == "refined"
    assert last_stage(["x"]) is None
    assert MULTIVIEW_METHODS == {"multiview", "multiview_refined"}


def test_the_pipeline_graph_wires_every_method():
    from common.evaluation.pipeline_graph import pipeline_graph
    doc = pipeline_graph("dataset", detector="oracle", refine=True, tracker=True)
    ids = {n["id"] for n in doc["nodes"]}
    for m, out in POSE_OUTPUTS.items():
        assert out.split("/")[0] in ids, m
    static = {n["id"] for n in pipeline_graph("dataset", detector="oracle", refine=True)["nodes"]}
    assert static == ids - {"tracker"}      # the tracker only for moving takes, or when asked
    assert "tracker" in {n["id"] for n in pipeline_graph("dataset", detector="oracle", methods=["tracked"])["nodes"]}


def test_method_names_are_listed_only_in_the_registry():
    """No other module spells three or more method names as one tuple, list or set literal, or
    as the keys of a table of constants (colours, outputs). Tables mapping methods to code (a
    bench's solver per method) are wiring, not lists."""
    names = set(POSE_METHODS)
    found = []
    for path in [*REPO.glob("common/**/*.py"), *REPO.glob("nodes/*.py")]:
        if path.name == "methods.py" and path.parent.name == "common":
            continue
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
                lits = {e.value for e in node.elts if isinstance(e, ast.Constant) and isinstance(e.value, str)}
                if len(lits & names) >= 3:
                    found.append(f"{path.relative_to(REPO)}:{node.lineno}")
            if isinstance(node, ast.Dict) and all(isinstance(v, ast.Constant) for v in node.values):
                keys = {k.value for k in node.keys if isinstance(k, ast.Constant) and isinstance(k.value, str)}
                if len(keys & names) >= 3:
                    found.append(f"{path.relative_to(REPO)}:{node.lineno}")
    assert not found, f"method lists outside common/methods.py: {found}"


"""The node reference (common/runtime/describe.py, docs/nodes.md) comes from the node classes."""
from common.runtime.describe import PAGE, as_text, describe, describe_main, field_docs, page
from common.runtime.params import merge_schemas


def test_the_committed_node_reference_is_current():
    assert PAGE.read_text() == page(), "docs/nodes.md is stale: run needletrack describe --all --markdown --out docs/nodes.md"


def test_a_node_is_described_from_its_class():
    info = describe("refine")
    assert ("left", "Keypoints") in info["inputs"] and info["outputs"] == ["pose", "no_pose", "lock", "one_camera"]
    params = {name: (tp, default, doc) for name, tp, default, doc in info["params"]}
    # the node's own params, the merged RefineConfig's, and the base class's, each with its comment
    assert params["max_wait"] == ("int", 30, "frames a pose (or a pair the solver needs the ECM pose for) waits for its ECM pose")
    assert params["sigma_kp_px"][2] == "assumed keypoint noise"
    assert params["min_cameras"][2].startswith("one camera poses the needle")   # the comment above it
    assert "refine" in as_text(info).splitlines()[0]
    det = {p[0] for p in describe("detector")["params"]}
    assert {"backend", "stride", "noise_px"} <= det        # the default backend's params too


def test_merged_schemas_remember_where_each_field_is_documented():
    from dataclasses import dataclass

    @dataclass
    class A:
        x: int = 1      # the x

    @dataclass
    class B:
        # the y, above
        y: float = 2.0

    docs = field_docs(merge_schemas("AB", A, B))
    assert docs == {"x": "the x", "y": "the y, above"}


def test_an_unknown_node_is_refused_with_a_suggestion(capsys):
    assert describe_main(["refne"]) == 2
    assert "did you mean 'refine'" in capsys.readouterr().err
    assert describe_main(["epnp"]) == 0 and "inputs:" in capsys.readouterr().out

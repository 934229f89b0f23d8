"""The evaluation/benchmark graph document and the lossless node wrapper, with no process."""
from common.evaluation.pipeline_graph import (
    SOURCE,
    keypoint_sources,
    lossless_class,
    pipeline_graph,
    pose_inputs,
)
from common.runtime.graph import graph_from_dict
from nodes.epnp import EpnpNode
from nodes.replay import ReplayNode


def test_pipeline_graph_is_valid_and_wired():
    doc = pipeline_graph("data/x", detector="oracle", refine=True, port=17447)
    g = graph_from_dict(doc)
    assert g.zenoh.listen == ["tcp/127.0.0.1:17447"]
    assert {"replay", "detector", "ecm", "epnp_average", "epnp_joint", "triangulate", "fusion",
            "refine", "fusion_refined"} == set(g.ids())
    assert all(n.restart == "never" for n in g.nodes)
    assert g.node("epnp_average").params["method"] == "average"
    assert g.node("fusion").inputs["pose"] == "epnp_joint/pose"
    assert g.node("fusion_refined").inputs["pose"] == "refine/pose"
    assert set(pose_inputs(doc)) == {"pnp_average", "pnp_joint", "triangulation", "multiview",
                                     "refined", "multiview_refined"}
    assert g.node(SOURCE).params["path"].endswith("data/x")


def test_split_detector_and_lossless_commands():
    doc = pipeline_graph("data/x", detector="learned", refine=False, split_detector=True,
                         lossless=True, sinks=[{"id": "sink", "module": "monitor"}])
    g = graph_from_dict(doc)
    assert "refine" not in g.ids() and "detector" not in g.ids()
    assert g.node("detector_left").inputs["left"] == "replay/left"
    assert "right" not in g.node("detector_left").inputs
    assert g.node("epnp_joint").inputs["left"] == keypoint_sources(True)["left"]
    n_main = len(g.nodes) - 1
    for n in g.nodes:
        if n.id == "sink":
            assert n.module == "monitor"      # sinks run as they are
            continue
        assert n.module is None and n.command[1:4] == ["-m", "common.evaluation.pipeline_graph", "--module"]
        assert n.command[4] in {"replay", "detector", "ecm", "epnp", "triangulate", "fusion"}
        peers = int(n.command[n.command.index("--peers") + 1])
        assert peers == (n_main + 2 if n.id == SOURCE else n_main)
    assert "--start-delay" in g.node(SOURCE).command


def test_lossless_class_keeps_every_input_and_pairs_deep():
    cls = lossless_class(EpnpNode)
    assert set(cls.KEEP_ALL) == set(EpnpNode.INPUTS) and issubclass(cls, EpnpNode)
    node = cls.offline({"method": "joint"})
    assert node.pairer.depth >= 1000
    assert lossless_class(ReplayNode, start_delay_s=1.0).KEEP_ALL == tuple(ReplayNode.INPUTS)   # its acks

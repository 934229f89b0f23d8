"""Typed node params: the required ones (``common.constraints.required``)."""
import pytest



def test_a_required_param_left_out_or_empty_is_refused_where_the_graph_declares_it():
    """A ``required`` param (``common.constraints.required``) is reported by ``param_errors``
    (what ``needletrack validate`` and the launcher's check read) when left out or empty."""
    from dataclasses import dataclass

    from common.constraints import required, required_fields
    from common.runtime.params import ParamError, param_errors, parse_params

    @dataclass
    class P:
        path: required("a dataset folder") = ""
        rate: float = 1.0

    assert required_fields(P) == {"path": "a dataset folder"}
    assert param_errors(P, {}) == ["params.path: is required (a dataset folder)"]
    assert param_errors(P, None) == ["params.path: is required (a dataset folder)"]
    assert param_errors(P, {"path": ""}) == ["params.path: is required (a dataset folder)"]
    assert param_errors(P, {"path": "data/x"}) == []
    with pytest.raises(ParamError, match="is required"):
        parse_params(P, {"rate": 2.0})
    assert parse_params(P, {"path": "data/x"}).path == "data/x"


def test_the_source_and_sink_nodes_declare_their_paths_required():
    from common.constraints import required_fields
    from nodes.evaluator import NODE as evaluator
    from nodes.recorder import NODE as recorder
    from nodes.replay import NODE as replay
    from nodes.rosbag import NODE as rosbag

    assert "path" in required_fields(replay.Params) and "path" in required_fields(rosbag.Params)
    assert "out" in required_fields(evaluator.Params) and "out" in required_fields(recorder.Params)

"""The geometry configs' constraints, declared on their fields (common/constraints.py): a
config built in code and a node param refuse the same values in the same words."""
import numpy as np
import pytest

from common.constraints import check_fields
from common.geometry.needle_tracker import TrackerConfig
from common.geometry.oracle import Oracle
from common.geometry.refine import RefineConfig
from common.runtime.params import param_errors


@pytest.mark.parametrize("kw, words", [
    ({"sigma_kp_px": -1}, "RefineConfig.sigma_kp_px: must be a positive number, got -1"),
    ({"sigma_kp_px": float("nan")}, "RefineConfig.sigma_kp_px: must be a positive number, got nan"),
    ({"max_depth_m": float("inf")}, "RefineConfig.max_depth_m: must be a positive number, got inf"),
    ({"max_iter": 0}, "RefineConfig.max_iter: must be at least 1, got 0"),
    ({"model_sigma_deg": -0.5}, "RefineConfig.model_sigma_deg: must be >= 0, got -0.5"),
    ({"rest_prior": 1.0}, r"RefineConfig.rest_prior: must be in \[0, 1\), got 1.0"),
])
def test_a_refine_config_built_in_code_is_refused_by_its_fields_constraint(kw, words):
    with pytest.raises(ValueError, match=f"^{words}$"):
        RefineConfig(**kw)


def test_numpy_scalars_and_the_defaults_pass_and_other_configs_place_their_refusal():
    assert RefineConfig(sigma_kp_px=np.float64(2.0), coarse_iter=np.int64(0)).coarse_iter == 0
    check_fields(RefineConfig())
    with pytest.raises(ValueError, match=r"^tracker: slip_sigma_m must be >= 0, got -1$"):
        TrackerConfig(slip_sigma_m=-1)
    with pytest.raises(ValueError, match=r"^oracle: missing_prob must be a probability in \[0, 1\], got 2$"):
        Oracle(missing_prob=2)
    with pytest.raises(ValueError, match=r"^oracle: centreline_noise_px must be >= 0"):
        Oracle(centreline_noise_px=-1.0)
    assert Oracle(centreline_noise_px=None).centreline_noise_px is None


def test_a_node_param_breaking_the_constraint_is_refused_where_the_graph_sets_it():
    from nodes.refine import RefineNode
    from nodes.tracker import TrackerNode
    assert param_errors(RefineNode.Params, {"sigma_kp_px": -1, "max_iter": 0, "min_score": 0.3}, "nodes[3].params") == [
        "nodes[3].params.sigma_kp_px: must be a positive number, got -1",
        "nodes[3].params.max_iter: must be at least 1, got 0"]
    assert param_errors(TrackerNode.Params, {"jaw_sigma_m": -1e-3}, "p") == ["p.jaw_sigma_m: must be >= 0, got -0.001"]

"""The fuzz target (``needletrack bench fuzz``) in small: poison payloads of every kind into every
input of every node of the default graph, in process; none may crash a handler or the codec,
publish a pose that breaks the invariant, or keep a node from publishing once clean frames
come again (the full count, 10,000 per input, is the bench command; docs/robustness.md)."""
import pytest
import logging

from common.robustness.fuzz import KINDS, RECOVERY_LIMIT, run_fuzz, summary
from common.runtime.graph import REPO_ROOT, load_graph


@pytest.mark.slow
def test_every_default_graph_node_survives_poison_on_every_input():
    logging.disable(logging.CRITICAL)
    try:
        results = run_fuzz(load_graph(REPO_ROOT / "dataflow.yaml"), per_input=2 * len(KINDS), seed=1,
                           log=lambda *a: None)
    finally:
        logging.disable(logging.NOTSET)
    s = summary(results)
    assert {r.node for r in results} >= {"camera", "detector_left", "detector_right", "ecm", "epnp_average",
                                          "epnp_joint", "triangulate", "fusion", "refine", "monitor"}
    crashes = [(r.node, r.input, r.first_crash) for r in results if r.crashes]
    assert not crashes
    assert s["invalid_poses_published"] == 0 and s["refused"] > 0 and s["delivered"] > 0
    late = [(r.node, r.input, r.recovery_frames) for r in results
            if r.recovery_frames is None or r.recovery_frames > RECOVERY_LIMIT]
    assert not late

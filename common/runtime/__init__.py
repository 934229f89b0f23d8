"""Runtime: nodes as processes on Eclipse Zenoh. Imports no geometry, sim, detector or evaluation.

``messages`` (the msgpack messages nodes exchange, validated at decoding), ``node`` (the node
base class, ``run``, ``node_class``), ``process`` (the process that hosts a node), ``inputs``
(its input queue), ``shm`` (shared memory), ``swap`` (hot swap, both sides), ``params`` (typed
node params), ``graph`` (the graph YAML: model, loading, keys), ``graph_checks`` (its
validation), ``zenoh_session`` (the Zenoh config: endpoints, TLS, access control), ``launcher``
(one process per node, restarts, spares), ``tools`` (``ps``, ``echo``, ``hz``, ``swap``,
``cmd``, ``validate``), ``pairing`` (stereo pairing by ``seq``), ``pacing`` (fixed-rate
sources), ``frame_stride`` (per-camera detectors on the same frames), ``camera_source`` (the
base of camera sources).

The entry points are re-exported here (``from common.runtime import Node, run``), each imported
when first used.
"""
from __future__ import annotations

import importlib

_EXPORTS = {
    "Node": "node", "NodeError": "node", "run": "node", "node_class": "node",
    "Graph": "graph", "GraphError": "graph", "NodeSpec": "graph", "load_graph": "graph",
    "graph_from_dict": "graph", "validate_graph": "graph_checks", "zenoh_config": "zenoh_session",
    "Launcher": "launcher", "Runtime": "process",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

"""The standard pose pipeline as a graph, and running it with its source started last.

``pipeline_graph`` builds, from ``dataflow.yaml``'s wiring with a replay for its camera and the
evaluation's params::

    replay -> detector -> epnp_average, epnp_joint -> triangulate -> ecm -> fusion
                       -> refine -> fusion_refined, tracker   (when nodes/refine.py exists)
                       -> evaluator / anything passed as ``sinks``

the pose methods' nodes chosen by the registry (``common.methods``: what each method needs).

``GraphRun`` launches every node but the source through ``common.runtime.launcher``, waits until each
one is live (its subscriptions are declared before its liveliness token), then starts the
source in a second launcher joined to the first, so no frame is published before its
consumers listen. The launchers' output (every node's log) goes to ``log`` (a file).
"""
from __future__ import annotations

import os
import socket
import sys
import threading
import time
from pathlib import Path
from typing import Optional

from common.detector.backends import backend_class
from common.errors import NeedletrackError
from common.frames import CAMERAS
from common.methods import BY_NAME, MULTIVIEW_METHODS, POSE_METHODS, POSE_OUTPUTS, requires
from common.runtime.graph import REPO_ROOT, graph_from_dict, live_key, module_info, parse_yaml
from common.runtime.messages import Calibration
from common.runtime.inputs import KEEP_ALL_LIMIT
from common.runtime.node import node_class
from common.runtime.pairing import StereoPairer

SOURCE = "replay"
LIVE_GRAPH = REPO_ROOT / "dataflow.yaml"
"""The graph whose wiring the evaluation graphs take (``pipeline_graph``)."""
LIVE_SOURCE = "camera"
"""Its source's id (the replay stands in for it)."""
LIVE_PARAMS_KEPT = ("method",)
"""The live graph's params an evaluation graph keeps: which method a node computes."""
LOSSLESS_TRACKER_WAIT = 900
"""Frames the lossless graph's tracker waits for a refined pose (the queues may hold it back so
long: the ECM poses run ahead of the refinement, 120 frames were passed on a machine shared with
a training, 71 of 391 poses then came too late); its fusions wait twice that for the tracker's
mode (the tracker waits on its pose). A frame the refinement answers sooner goes at once."""


def free_port() -> int:
    """A free TCP port on 127.0.0.1 (the OS picks it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def has_module(name: str) -> bool:
    info = module_info(name)
    return info is not None and info["has_node"] and not info["syntax_error"]


def live_graph_nodes() -> dict:
    """``dataflow.yaml``'s nodes by id, as parsed (the wiring every evaluation graph starts from)."""
    doc = parse_yaml(LIVE_GRAPH.read_text(), str(LIVE_GRAPH))
    return {n["id"]: n for n in doc["nodes"]}


def wanted_methods(methods=None, *, refine: bool = True, tracker: bool = False) -> list:
    """The pose methods a graph runs, in the registry's order: ``methods`` (default: every one,
    ``tracked`` only with ``tracker``) and every method they take poses from
    (``common.methods.requires``); without ``refine``, none that is or needs ``refined``."""
    wanted = set(POSE_OUTPUTS) if methods is None else set(methods)
    if methods is None and not tracker:
        wanted.discard("tracked")
    unknown = wanted - set(POSE_OUTPUTS)
    if unknown:
        raise ValueError(f"unknown pose method(s) {sorted(unknown)}; known: {', '.join(POSE_OUTPUTS)}")
    if not refine:
        wanted = {m for m in wanted if m != "refined" and "refined" not in requires(m)}
    for m in list(wanted):
        wanted |= requires(m)
    return [m for m in POSE_METHODS if m in wanted]


def method_node(live: dict, method: str) -> dict:
    """The live graph's node that produces ``method``; a multi-view method the live graph does not
    run is its other fusion node, fusing ``method``'s single-frame poses."""
    nid = POSE_OUTPUTS[method].split("/")[0]
    if nid in live:
        return live[nid]
    fuses = BY_NAME[method].fuses
    template = next((live[o.split("/")[0]] for m, o in POSE_OUTPUTS.items()
                     if fuses and m in MULTIVIEW_METHODS and o.split("/")[0] in live), None)
    if template is None:
        raise ValueError(f"{LIVE_GRAPH.name} has no node {nid!r} for the method {method!r}")
    return {**template, "id": nid, "params": {**template.get("params", {}), "method": method},
            "inputs": {**template.get("inputs", {}), "pose": POSE_OUTPUTS[fuses]}}


def pipeline_graph(dataset: str, *, detector: str = "learned", detector_params: Optional[dict] = None,
                   rate="max", port: Optional[int] = None, name: str = "needletrack-eval",
                   refine: Optional[bool] = None, loop: bool = False, count: int = 0,
                   sinks: Optional[list] = None, lossless: bool = False,
                   split_detector: bool = False, methods=None,
                   start_delay_s: float = 1.0, decode: bool = False,
                   refine_tracking: bool = True, refine_params: Optional[dict] = None,
                   tracker: bool = False, tracker_params: Optional[dict] = None,
                   replay_params: Optional[dict] = None, cameras: tuple = CAMERAS) -> dict:
    """The graph document of the whole pipeline on a replayed dataset folder: ``dataflow.yaml``'s
    wiring (module, inputs, outputs of each node) with these overrides:

    - the source is a ``replay`` of ``dataset`` (id ``replay``, for the live graph's ``camera``);
    - the detector: the live graph's two per-camera nodes (``split_detector``), or one node for
      both cameras; ``backend: detector`` and ``detector_params`` are its params;
    - the pose nodes: those of the methods wanted (``wanted_methods``); an input from a node
      that does not run is left out (the fusions take the tracker's modes only where it runs);
    - params: the evaluation's, not the live graph's tuning (its scene prior, the detector's
      tracking): of the live params only ``method`` (which method a node computes) is kept.

    ``refine``: include the refinement node and what takes its poses (default: when
    nodes/refine.py exists). ``methods``: only the nodes these pose methods (names of
    ``POSE_OUTPUTS``) need, e.g. ``["multiview_refined"]`` runs replay, detector, ecm, refine
    and fusion_refined (default: every method). ``sinks``: extra node dicts (e.g. the evaluator), wired by the
    caller with the ids used here. Every node runs with ``restart: never``: a run that loses a
    node is a failed run, not one to patch up silently.

    ``lossless``: every pipeline node runs through ``lossless_command``: each of its inputs
    queues every message instead of keeping the newest (an evaluation scores every frame,
    whatever the machine's load; the tracker then waits for every frame's refined answer, not
    for the source's end of stream, which comes tens of seconds earlier on a loaded machine), the source waits ``start_delay_s`` after joining the
    graph before its first frame, so that its links to every consumer are up, and stamps the
    frames with their recorded timing (the replay's ``stamps: recorded``): the tracker's motion
    models see the takes' own time, not the replay's pace. ``decode``: the
    replay decodes the images once at start-up and sends them raw, as a live camera would.
    ``refine_tracking``: the refinement starts a frame from the last one's pose when it can
    (``common.geometry.refine_tracking``; false: every frame on its own, a single-frame method);
    ``refine_params``: more params of the refine node (e.g. ``support_normal_world``).
    ``tracker``: also the tracker node (method ``tracked``: the refined poses over time with the
    instruments' states, docs/tracking.md), for folders of moving takes; also when ``methods``
    names ``tracked``. ``tracker_params``: its params. Where the tracker runs, the fusions take
    its poses (``motion``): they fuse only the frames whose needle it says is at rest.
    ``rate="paced"``: the replay sends the next frame once both cameras' keypoints of the last
    one are out (closed loop, as fast as the graph goes); the detectors then take every frame.
    ``replay_params``: more params of the replay (e.g. ``withhold``: one camera's images black for
    a share of each take). ``cameras``: one camera (``("left",)``) is a monocular endoscope: only
    its detector, the refinement on its images alone and the tracker (``start_one_camera``): the
    methods ``refined`` (which then poses nothing: its poses are on ``refine/one_camera``) and
    ``tracked`` only.
    """
    cameras = tuple(c for c in CAMERAS if c in cameras)
    if not cameras:
        raise ValueError(f"cameras: some of {CAMERAS}")
    monocular = len(cameras) == 1
    if monocular:
        tracker = True
        methods = ["tracked"]
        split_detector = True
    if refine is None:
        refine = has_module("refine")
    wanted = wanted_methods(methods, refine=refine, tracker=tracker)
    live = live_graph_nodes()
    port = port or free_port()
    one = {"OMP_NUM_THREADS": "1"}
    det_params = {"backend": detector, **(detector_params or {})}
    paced = str(rate) == "paced"
    if paced:
        det_params.setdefault("stride", 1)    # the replay waits for every frame's keypoints
    # only a backend that reads the ground truth (the oracle) gets it: every message costs
    # each receiving process ~0.3 ms of CPU
    truth = {"truth": f"{SOURCE}/truth"} if backend_class(detector).needs_truth else {}
    if split_detector and detector == "learned":
        det_params.setdefault("threads", 1)   # two processes share the cores, one each
    kp = keypoint_sources(split_detector)
    live_kp = {keypoint_sources(True)[cam]: kp[cam] for cam in CAMERAS}

    def rename(src: str) -> str:
        """Where an output of the live graph comes from here."""
        node, _, out = src.partition("/")
        return f"{SOURCE}/{out}" if node == LIVE_SOURCE else live_kp.get(src, src)

    def wire(n: dict, params: dict, inputs: Optional[dict] = None, env: Optional[dict] = one) -> dict:
        ins = {k: rename(src) for k, src in n.get("inputs", {}).items()}
        ins.update(inputs or {})
        kept = {k: v for k, v in (n.get("params") or {}).items() if k in LIVE_PARAMS_KEPT}
        out = {"id": n["id"], "module": n["module"], "params": {**kept, **params}, "inputs": ins,
               "outputs": list(n["outputs"])}
        if env:
            out["env"] = dict(env)
        return out

    nodes = [{"id": SOURCE, "module": "replay",
              "params": {"path": str(Path(dataset).resolve()), "rate": rate, "loop": bool(loop),
                         "count": int(count), "decode": bool(decode),
                         **({"stamps": "recorded"} if lossless else {}), **(replay_params or {})},
              "outputs": list(module_info("replay")["outputs"])}]
    if paced:
        nodes[0]["inputs"] = {"ack": kp["left"], "ack2": kp["right"]}
    per_camera = [live[f"detector_{cam}"] for cam in cameras]
    if split_detector:   # one process per camera: the two images are detected in parallel
        nodes += [wire(n, dict(det_params), truth) for n in per_camera]
    else:                # the two per-camera nodes as one
        joined = {"id": "detector", "module": "detector",
                  "inputs": {k: v for n in per_camera for k, v in n["inputs"].items()},
                  "outputs": [o for n in per_camera for o in n["outputs"]]}
        nodes.append(wire(joined, det_params, truth, env=None))
    nodes.append(wire(live["ecm"], {}, {"measured": f"{SOURCE}/measured"}))
    # lossless: a pose (refine: a pair) waits for its frame's ECM pose as long as the queues may
    # hold that back (a starved ecm process falls frames behind the keypoints on a loaded machine);
    # the tracker waits as long for a refined pose, the fusions twice that for the tracker's mode
    pose_wait = {"max_wait": LOSSLESS_TRACKER_WAIT} if lossless else {}
    fusion_wait = {"max_wait": (2 if "tracked" in wanted else 1) * LOSSLESS_TRACKER_WAIT} if lossless else {}
    params = {"refined": {"tracking": bool(refine_tracking), **pose_wait, **(refine_params or {})},
              "tracked": {**pose_wait, **({"start_one_camera": True} if monocular else {}), **(tracker_params or {})}}
    for m in wanted:
        n = method_node(live, m)
        p = fusion_wait if m in MULTIVIEW_METHODS else params.get(m, pose_wait)
        # the tracker steps the frames still waiting at the source's end of stream; not in a lossless
        # graph, where the refinement answers every frame but may lag the source by tens of seconds
        nodes.append(wire(n, dict(p), {"eos": f"{SOURCE}/eos"} if m == "tracked" and not lossless else None))
    ids = {n["id"] for n in nodes}
    for n in nodes:   # wire only what a module declares (optional inputs come and go) and what runs
        info = module_info(n["module"])
        if "inputs" in n:
            n["inputs"] = {k: v for k, v in n["inputs"].items()
                           if v.split("/")[0] in ids and (not info or info["inputs"] is None or k in info["inputs"])}
    wrapped = list(nodes) if lossless else []
    nodes += list(sinks or [])
    # every process of the graph but the source, plus the launcher that hosts them
    n_main = len(nodes) - 1
    for n in wrapped:
        source = n["id"] == SOURCE
        # a node waits for its links to every other node (and the hub, and for the source its
        # own launcher) before it goes live; the source then also waits start_delay_s
        feedback = (module_info(n["module"]) or {}).get("feedback") or []
        if feedback:
            n["feedback"] = [k for k in feedback if k in n.get("inputs", {})]   # a command hides FEEDBACK
        n["command"] = lossless_command(n.pop("module"), start_delay_s if source else 0.0,
                                        peers=n_main + 2 if source else n_main)
    for n in nodes:
        n.setdefault("restart", "never")
    return {"graph": name, "zenoh": {"mode": "peer", "listen": [f"tcp/127.0.0.1:{port}"]},
            "nodes": nodes}


def keypoint_sources(split_detector: bool) -> dict:
    """``{"left": "node/output", "right": ...}``: where the detector's keypoints come out."""
    if split_detector:
        return {"left": "detector_left/left", "right": "detector_right/right"}
    return {"left": "detector/left", "right": "detector/right"}




def recorder_node(doc: dict, out_file, split_detector: bool, cameras: tuple = CAMERAS) -> dict:
    """The ``recorder`` node (nodes/recorder.py) for graph ``doc``: each refined pose (where the
    graph refines both cameras' views), each pose fitted to one camera's view and each camera's
    keypoints to ``out_file`` as JSON lines (``common.evaluation.recording``)."""
    refine = any(n["id"] == "refine" for n in doc["nodes"])
    poses = {"one_camera": "refine/one_camera", **({"pose": "refine/pose"} if len(cameras) == 2 else {})}
    return {"id": "recorder", "module": "recorder", "params": {"out": str(Path(out_file).resolve())},
            "inputs": {"eos": f"{SOURCE}/eos", **(poses if refine else {}),
                       **{c: src for c, src in keypoint_sources(split_detector).items() if c in cameras}},
            "restart": "never"}


def pose_inputs(doc: dict) -> dict:
    """Input wiring ``method -> node/output`` for the pose methods present in a graph doc."""
    ids = {n["id"] for n in doc["nodes"]}
    return {m: src for m, src in POSE_OUTPUTS.items() if src.split("/")[0] in ids}


class GraphRunError(NeedletrackError, RuntimeError):
    """A graph run that failed: a node died, never came up, or the run timed out."""


class GraphRun:
    """Run a graph with its source started last (see the module docstring).

    ``wait_for``: node ids whose exit ends the run (e.g. ``["evaluator"]``); ``run(timeout)``
    returns when they all exited with status 0 and raises ``GraphRunError`` when any node exits
    with another status, a node is not live within ``ready_timeout`` or ``timeout`` passes.
    """

    def __init__(self, doc: dict, log, source: str = SOURCE, ready_timeout: float = 120.0):
        from common.runtime.launcher import Launcher
        self.graph = graph_from_dict(doc)
        self.source = source
        self.ready_timeout = ready_timeout
        self.log = log
        rest = [i for i in self.graph.ids() if i != source]
        self.main = Launcher(self.graph, only=rest, out=log)
        self.src = None
        self.session = None
        self._threads: list = []

    def client_session(self):
        """A client session on the hub: it sees the graph's liveliness and data, and, unlike a
        peer, is no link the nodes wait for."""
        if self.session is None:
            import zenoh

            from common.runtime.zenoh_session import zenoh_config
            c = zenoh_config(self.main.graph, role="node")    # the operator's identity on the run's credentials
            c.insert_json5("mode", '"client"')
            c.insert_json5("listen/endpoints", "[]")
            self.session = zenoh.open(c)
        return self.session

    def live_nodes(self) -> set:
        live = set()
        for reply in self.client_session().liveliness().get(live_key(self.graph.name), timeout=1.0):
            if reply.ok is not None:
                live.add(str(reply.ok.key_expr).rsplit("/", 1)[-1])
        return live

    def dead_nodes(self, launcher) -> dict:
        """Nodes of ``launcher`` that exited with a status other than 0: id -> status."""
        return {nid: s.last_status for nid, s in list(launcher.slots.items())
                if s.done and s.last_status not in (0, None)}

    def start(self) -> None:
        """Start every node, the source last (``start_consumers`` then ``start_source``)."""
        self.start_consumers()
        self.start_source()

    def start_consumers(self) -> None:
        """Start every node but the source and wait until each is live."""
        self.main.start()
        self._threads.append(threading.Thread(target=self.main.run, name="launcher", daemon=True))
        self._threads[-1].start()
        want = set(self.main.only)
        deadline = time.monotonic() + self.ready_timeout
        while True:
            dead = self.dead_nodes(self.main)
            if dead:
                raise GraphRunError(f"node(s) failed while starting: {_fmt_dead(dead)}")
            missing = want - self.live_nodes()
            if not missing:
                break
            if time.monotonic() > deadline:
                raise GraphRunError(f"node(s) not up after {self.ready_timeout:.0f} s: {', '.join(sorted(missing))}")
            time.sleep(0.2)

    def start_source(self) -> None:
        """Start the source (in a second launcher joined to the first)."""
        from common.runtime.launcher import Launcher
        time.sleep(0.3)   # let the declarations settle across the peers
        self.src = Launcher(self.graph, only=[self.source], out=self.log)
        self.src.start()
        self._threads.append(threading.Thread(target=self.src.run, name="launcher-src", daemon=True))
        self._threads[-1].start()

    def failed(self) -> dict:
        """Nodes of the run that exited with a status other than 0: id -> status."""
        dead = {}
        for l in (self.main, self.src):
            if l is not None:
                dead.update(self.dead_nodes(l))
        return dead

    def wait(self, until: list, timeout: float) -> None:
        """Block until every node in ``until`` exited with 0 (see the class docstring)."""
        deadline = time.monotonic() + timeout
        while True:
            dead = self.failed()
            if dead:
                raise GraphRunError(f"node(s) failed: {_fmt_dead(dead)}")
            done = True
            for nid in until:
                l = self.main if nid in self.main.slots else self.src
                s = l.slots[nid]
                done &= s.done and s.last_status == 0
            if done:
                return
            if time.monotonic() > deadline:
                raise GraphRunError(f"timed out after {timeout:.0f} s waiting for {', '.join(until)}")
            time.sleep(0.1)

    def stop(self) -> None:
        if self.session is not None:
            try:
                self.session.close()
            except Exception:
                pass
            self.session = None
        for l in (self.src, self.main):
            if l is not None:
                l.stop()
        for t in self._threads:
            t.join(15.0)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()


def _fmt_dead(dead: dict) -> str:
    from common.runtime.launcher import describe_status
    return ", ".join(f"{nid} ({describe_status(code)}{'; bad configuration' if code == 2 else ''})"
                     for nid, code in sorted(dead.items()))


# ---------------------------------------------------------------- lossless nodes

PEER_WAIT_S = 30.0


def lossless_command(module: str, start_delay_s: float = 0.0, peers: int = 0) -> list:
    """The ``command`` that runs ``nodes/<module>.py`` with every input keeping every message
    (see ``lossless_class``)."""
    cmd = [sys.executable, "-m", "common.evaluation.pipeline_graph", "--module", module]
    if start_delay_s > 0:
        cmd += ["--start-delay", f"{start_delay_s:g}"]
    if peers > 0:
        cmd += ["--peers", str(peers)]
    return cmd


def lossless_class(base: type, start_delay_s: float = 0.0, peers: int = 0) -> type:
    """A subclass of a node class whose inputs are all keep-all (and whose stereo pairers, if
    any, hold as many frames as those queues).

    After its setup (its Zenoh session is open by then; its liveliness token is declared after)
    it waits until the session has direct links to ``peers`` peers (at most PEER_WAIT_S): peers
    find each other by gossip through the hub, and a message published before the link to a
    subscriber is up never reaches it. Then it waits ``start_delay_s`` more.
    """
    attrs = {"KEEP_ALL": tuple(base.INPUTS), "__module__": base.__module__,
             "__doc__": f"{base.__name__}, every input keeping every message."}

    def setup(self):
        base.setup(self)
        # stereo pairing waits for a frame's other half as long as the queues hold it
        for value in vars(self).values():
            if isinstance(value, StereoPairer):
                value.depth = max(value.depth, KEEP_ALL_LIMIT)
        rt = getattr(self, "_runtime", None)
        session = getattr(rt, "session", None)
        if peers > 0 and session is not None:
            deadline = time.monotonic() + PEER_WAIT_S
            while len(list(session.info.peers_zid())) < peers:
                if time.monotonic() > deadline:
                    self.log.warning("linked to %d of %d peers after %.0f s; going on",
                                     len(list(session.info.peers_zid())), peers, PEER_WAIT_S)
                    break
                time.sleep(0.05)
        if start_delay_s > 0:
            time.sleep(start_delay_s)
            # a source that holds its calibration sends it ahead of the first frame: messages
            # on different keys may overtake each other, and a frame without calibration is lost
            calib = getattr(self, "calib", None)
            if isinstance(calib, Calibration) and "calib" in self.OUTPUTS:
                self.publish("calib", calib)
                time.sleep(0.2)
    attrs["setup"] = setup
    return type(base.__name__, (base,), attrs)


def _lossless_main(argv=None) -> int:
    """``python -m common.evaluation.pipeline_graph --module M [--start-delay S]``, started by the launcher
    as a command node (graph file and node id from NEEDLETRACK_GRAPH / NEEDLETRACK_NODE)."""
    import argparse
    ap = argparse.ArgumentParser(prog="python -m common.evaluation.pipeline_graph")
    ap.add_argument("--module", required=True)
    ap.add_argument("--start-delay", type=float, default=0.0)
    ap.add_argument("--peers", type=int, default=0)
    args = ap.parse_args(argv)
    from common.runtime.node import run
    graph, node = os.environ.get("NEEDLETRACK_GRAPH"), os.environ.get("NEEDLETRACK_NODE")
    if not graph or not node:
        print("common.evaluation.pipeline_graph: NEEDLETRACK_GRAPH and NEEDLETRACK_NODE must be set "
              "(run by the launcher)", file=sys.stderr)
        return 2
    base = node_class(args.module)
    return run(lossless_class(base, args.start_delay, args.peers), ["--graph", graph, "--node", node])


if __name__ == "__main__":
    sys.exit(_lossless_main())

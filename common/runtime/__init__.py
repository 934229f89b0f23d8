"""Runtime: nodes as processes on Eclipse Zenoh, their messages, graphs, the launcher and the
graph tools. Imports no geometry, sim, detector or evaluation.

Modules (``python -m common.layout`` writes this list from their docstrings):

- ``camera_source``: Base of the camera source nodes (``sim``, ``replay``): the calibration beacon.
- ``certs``: ``needletrack certs``: a test CA and one certificate per member of a graph.
- ``checks``: The checks a message's fields pass at decoding and at publishing: the limits (finite,
  bounded; the fields declare them, ``common.runtime.schema``), rigid transforms, covariances, image
  headers, the pose invariant.
- ``codec``: The messages' msgpack codec (no pickle): ``{"schema": NAME, "version": V, "body":
  {...}}``, numpy arrays as a msgpack extension (dtype, shape, raw bytes) that round-trips exactly,
  a large bytes field (an image) as the payload's tail, handed out by ``decode`` as a view.
- ``credentials``: Per-run credentials: a local graph that no other process can steer, by default.
- ``describe``: The node reference: what a node takes, gives and accepts, read from its class.
- ``frame_stride``: Which frames a detector that cannot keep up with the camera should take.
- ``graph``: The dataflow graph (``dataflow.yaml``): its model (``Graph``, ``NodeSpec``, the Zenoh
  and TLS settings), loading, key names and the node modules it names.
- ``graph_checks``: The graph YAML checked: ``validate_graph`` (every error at once, each with its
  place), ``graph_cycles``, ``graph_warnings`` (what runs but is risky: a graph open to other
  hosts).
- ``inputs``: A node's pending input messages: ``InputQueue`` (newest-only and keep-all inputs).
- ``launcher``: The launcher: runs a graph as one process per node, supervises and hot-swaps them.
- ``limits``: Limits on input read from disk: a YAML loader with a node budget, and an image-file
  reader that checks size and header before it reads or decodes (see docs/robustness.md).
- ``messages``: Messages the dataflow carries, and their msgpack codec (no pickle).
- ``node``: The node runtime: a ``Node`` base class and ``run`` that hosts one node in one process.
- ``pacing``: Pacing of a source: what a source promises about when its frames go out (``Pacer``),
  and a recorded source's ``rate`` (``parse_rate``, ``SourceClock``, ``AckWindow``).
- ``pairing``: Joining a node's inputs by frame ``seq``: stereo pairing of per-camera messages
  (``StereoPairer``), messages held until the rest of their frame is in (``SeqJoin``), the same
  declared input by input (``FrameJoin``, ``Wait``: which inputs a frame waits for, which it needs,
  how long), a bounded cache keyed by ``seq`` (``SeqCache``), and the frame clock (``SeqClock``)
  that tells a node when its source restarted or a seq is poison.
- ``params``: Typed node params: a node declares them once as a dataclass, the graph's YAML fills
  them.
- ``process``: The process that hosts one node (``common.runtime.node.run``, docs/runtime.md):
- ``schema``: The one schema mechanism (msgspec): a field is declared once, as its type annotation
  with its constraints on it, and converted strictly; a refusal is placed: ``Owner.field: why``.
- ``shm``: Zenoh shared memory for large payloads (images): ``ShmWriter``.
- ``swap``: Hot swap, both sides: the launcher's (``LauncherSwap.swap``) and the process's
  (``SwapControl``, the handover and takeover queries).
- ``tools``: Graph tools of the CLI: ``validate``, ``ps``, ``echo``, ``hz``, ``swap``, ``cmd``.
- ``zenoh_session``: The Zenoh session a graph configures: ``zenoh_config`` (mode, endpoints, shared
  memory, mutual TLS), ``access_control`` (who may put, subscribe and query what), the TLS files
  each identity needs, ``close_session``.
"""

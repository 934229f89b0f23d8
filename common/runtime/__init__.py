"""Runtime: nodes as processes on Eclipse Zenoh. Imports no geometry, sim, detector or evaluation.

``messages`` (the msgpack messages nodes exchange, validated at decoding), ``node`` (the node
base class and the process that hosts it), ``params`` (typed node params), ``graph`` (the graph
YAML: parsing, validation, keys), ``launcher`` (one process per node, restarts, hot swap),
``tools`` (``ps``, ``echo``, ``hz``, ``swap``, ``cmd``, ``validate``), ``pairing`` (stereo
pairing by ``seq``), ``pacing`` (fixed-rate sources), ``frame_stride`` (per-camera detectors on
the same frames), ``camera_source`` (the base of camera sources).
"""

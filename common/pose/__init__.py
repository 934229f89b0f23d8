"""Per-frame pose decisions: what a pose node does with one frame's inputs, as plain classes
that take messages and return the messages to publish, tested without Zenoh (the nodes in
``nodes/`` only wire them). Imports ``geometry``, ``runtime`` (messages, the frame joins of
``pairing``) and ``data`` (the instruments' table size).

``stereo`` (the stereo pose nodes' frame: pairing by ``seq``, the frame's ECM pose, the end
identity read and stated; ``StereoPoseStep``, ``PnpStep``, ``TriangulationStep``),
``refine_step`` (the dense refinement's frame: gates, partial views, the tip's caps;
``RefineStep``), ``tracker_step`` (the tracker's frame: the measurement a pose gives, late
poses replayed, the instruments' table, the published pose; ``TrackerStep``).

Modules (``python -m common.layout`` writes this list from their docstrings):

- ``refine_step``: The frame step of the dense refinement (the ``refine`` node): the needle pose
  fitted to its whole visible arc in both cameras, with an uncertainty (``common.geometry.refine``).
- ``stereo``: The frame step of the stereo pose nodes (``epnp``, ``triangulate``, ``refine``): a
  stereo frame's two ``Keypoints`` to a ``PoseEstimate``.
- ``tracker_step``: The frame step of the tracker (the ``tracker`` node): refined poses and the
  instruments' states to the tracked pose and the needle in the jaws
  (``common.geometry.needle_tracker``, docs/tracking.md).
"""

"""Hand labels of a dataset folder's frames in the browser (``needletrack label DIR``,
docs/label.md). May import ``geometry``, ``data``, ``runtime``, ``detector`` (its backends'
public API, the wire's sub-pixel centreline) and ``viewer`` (the HTTP server, the browser
harness).

Modules (``python -m common.layout`` writes this list from their docstrings):

- ``fit``: The needle fitted through a user's clicks: the pose whose projected arc passes through
  them, and the labels it gives (keypoints A..E with visibility, box, pose, their stated noise).
- ``page``: The labelling page (HTML and JavaScript, no library): both cameras on canvases with zoom
  (wheel) and pan (right or middle drag, or shift + drag); a click places the tip, then the tail,
  then points on the wire; the server fits the arc after every change and the page draws it with
  A..E.
- ``proposals``: The detector's proposals for a folder's frames and the order in which they are
  labelled.
- ``server``: ``needletrack label DIR``: the labelling page over a dataset folder, served on
  127.0.0.1 (``common.viewer.http_server``: the Host and Origin checks, the bounds), docs/label.md.
- ``simulate``: Simulated clicks: what a user would click on a frame whose true pose is known, with
  a stated error, for the benchmark of the labels (``needletrack bench label``) and for learning
  curves that label a train split without a person, through the same code path as the page
  (``LabelApp.save``).
- ``store``: Hand labels kept in a dataset folder: each labelled frame's line of frames.jsonl gets
  the contract's ground-truth fields (``keypoints``, ``visible``, ``bbox``, ``T_world_needle`` where
  the stereo fit gives a sure pose) and needletrack's own ``label`` field (docs/datasets.md: the
  clicks, the stated noise, the pose in the ECM frame).
- ``targets``: Which frames of a hand-labelled folder are training targets (``needletrack
  finetune``, docs/adapt.md).
"""

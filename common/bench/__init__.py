"""The ``needletrack bench NAME`` benchmarks: speed and accuracy of each stage and of the whole
graph. May import ``evaluation`` and every package above it.

Modules (``python -m common.layout`` writes this list from their docstrings):

- ``detector_bench``: ``needletrack bench detector``: speed and accuracy of a keypoint detector
  backend.
- ``end_identity_bench``: ``needletrack bench end-identity``: how well the learned detector tells
  the tip from the tail.
- ``familiarity_bench``: ``needletrack bench familiarity``: how unlike the detector's training looks
  each folder's images are, and (``--fit FILE``) the reference that measures it
  (``common.detector.familiarity``).
- ``folder_detections``: The learned detector run cold over a dataset folder's images: the loop the
  end-identity and familiarity benchmarks (and ``needletrack adapt``'s refit) share.
- ``geometry_bench``: Measure the geometry methods on the oracle: pose error against keypoint noise,
  and speed.
- ``graph_bench``: ``needletrack bench [graph] [--dataset DIR]``: the live pipeline's speed, end to
  end.
- ``held_bench``: ``needletrack bench held``: the keypoint detector on moving takes, by how much of
  the needle is seen.
- ``label_bench``: ``needletrack bench label --dataset DIR``: how good hand labels are, by simulated
  clicks on a folder with ground truth.
- ``presence_bench``: ``needletrack bench presence``: where the detector reports a needle that is
  not there, and (``--fit FILE``) the presence gate that keeps those reports under a share
  (``common.detector.presence_gate``).
- ``refine_bench``: ``needletrack bench refine``: speed and accuracy of the dense refinement on
  synthetic frames.
- ``restart_bench``: ``needletrack bench restart``: how long the graph is without poses after ``kill
  -9`` of its camera.
- ``ros_bench``: ROS benchmarks (figures in docs/ros.md).
- ``sim_bench``: ``needletrack bench sim``: how fast the built-in scene renders stereo frames, and
  their size.
- ``tracker_bench``: ``needletrack bench tracker``: the needle tracker
  (``common.geometry.needle_tracker``) alone, on the motion scripts' exact takes, no rendering.
- ``transport_bench``: ``needletrack bench transport``: 1920x1080 stereo frames between two node
  processes.
"""

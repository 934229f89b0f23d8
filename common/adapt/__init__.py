"""The detector on a user's own footage: ``needletrack detect`` (its detections on a user's
files), ``needletrack adapt`` (fitting without labels) and ``needletrack finetune`` (fitting from
hand labels; docs/adapt.md). May import ``evaluation``, ``bench`` and every package above them.

Modules (``python -m common.layout`` writes this list from their docstrings):

- ``adapt``: ``needletrack adapt --data DIR [--data DIR ...] --out OUT``: fit the detector to a
  user's scene from recordings without ground truth (docs/adapt.md).
- ``adapt_calibration``: The adapted weights' familiarity and end-identity coefficients, fitted
  without ground truth.
- ``adapt_run``: The shipped pipeline over a folder without ground truth, its outputs kept for
  ``needletrack adapt``.
- ``detect_files``: ``needletrack detect PATH [PATH ...] --out DIR``: the keypoint detector on a
  user's own images, videos and folders, without a graph, calibration or ground truth
  (docs/commands.md).
- ``finetune``: ``needletrack finetune --labels DIR [--labels DIR ...] --out OUT``: fit the detector
  to a user's footage from frames labelled by hand (``needletrack label``; docs/adapt.md).
- ``finetune_report``: Before and after a fine-tune, on the user's held-out hand-labelled frames
  (``needletrack finetune``'s report, docs/adapt.md): the weights run cold on each held-out image
  through the detector backend's public API (``learned``, whatever network the weights hold), scored
  against the labels:
- ``learning_curve``: The hand-label learning curve: what 10, 30 and 100 labelled stereo frames buy
  on a look.
- ``pseudo_labels``: Pseudo-labels without ground truth: the world pose of a static needle that the
  pipeline's views agree on, projected back into every image of the group as its training labels.
"""

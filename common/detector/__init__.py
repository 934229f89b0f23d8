"""The keypoint detector: the network, its training, inference and the detector backends. Imports
``geometry``, ``data`` (its ``DatasetError``) and ``runtime`` (messages).

Modules (``python -m common.layout`` writes this list from their docstrings):

- ``arc_fit``: The needle's arc from the network's outputs: the centreline decoded from its logits,
  the perspective image of the arc (an affine image of a circle) fitted through A, E and the
  centreline, and B..D placed on it (image pixels, angles along the arc in degrees).
- ``backbone``: EfficientNet-Lite0's trunk (Tan & Le 2019; the Lite variant: no squeeze-excite,
  ReLU6), pretrained on ImageNet, as the learned detector's encoder.
- ``backends``: Keypoint detector backends: the interface the ``detector`` node runs, and a lazy
  registry.
- ``batches``: What ``needletrack train`` (``common.detector.train``) trains on: stage-2 crop
  batches (the keypoints, the centreline, presence; with mined hard negatives,
  ``mine_hard_negatives``) and stage-1 global batches (the needle's box).
- ``centreline_subpixel``: Sub-pixel needle centreline from the full-resolution image, along a
  coarse curve's normals.
- ``classical``: The classical needle detector (OpenCV only, no learning): the baseline that shows
  what the learned detector buys.
- ``config``: The detectors' configs, one per algorithm: ``DetectorConfig`` (the learned two-stage
  detector, ``common.detector.inference``) and ``ClassicalConfig`` (the image-processing baseline).
- ``cut_ends``: An end keypoint where something covers the wire: the needle goes on under it.
- ``data``: Needle datasets -> training samples for the learned keypoint detector.
- ``detections_file``: ``detections.jsonl``: what the detector found in each image of a user's
  files, one JSON object a line (``needletrack detect``; its fields:
  docs/commands.md#needletrack-detect).
- ``end_identity``: Which end of a detected needle is the tip: evidence from the needle's own shape
  and from the network, as the probability that keypoint A is where the detector says.
- ``familiarity``: How unlike the detector's training data an image looks, from the network's own
  features.
- ``inference``: Inference with the learned keypoint detector: image -> ``Keypoints`` (A..E, scores,
  centreline).
- ``learned``: The detector node's ``learned`` backend: the keypoint network (``KeypointDetector``)
  behind the backend interface (``common.detector.backends``), with the calibration's lens
  distortion.
- ``model``: The learned needle detector's two networks, their losses, and decoding to sub-pixel
  keypoints.
- ``presence_gate``: The presence gate fitted for a weights file: the stage-2 presence a needle must
  reach to be reported, chosen on looks the weights never trained on (``presence_gate.json`` beside
  them; ``needletrack bench presence --fit``).
- ``ridge_ends``: The needle's two ends from the centreline heatmap, when the tip and tail heatmaps
  lose one.
- ``synthetic``: A small needle dataset drawn with OpenCV, in the format of docs/dataset.md: an arc
  with a tapered tip and a thread on a textured background.
- ``train``: ``needletrack train``: train the learned keypoint detector on a needle dataset, on the
  CPU.
- ``weights``: The keypoint network's weights file: loading (``torch.load(..., weights_only=True)``,
  never a pickle of code), its format check, the end-identity coefficients fitted for it, and the
  device.
"""

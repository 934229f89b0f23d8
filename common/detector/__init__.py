"""The keypoint detector. Imports ``geometry`` and ``runtime`` (messages).

``model`` (the network), ``data`` (training samples from dataset folders), ``train`` (the
``needletrack train`` command), ``batches`` (what it trains on), ``inference``
(``KeypointDetector`` and the ``learned`` backend), ``centreline_subpixel`` (the arc's
centreline in the full-resolution image), ``classical`` (an image-processing baseline), ``backends`` (the backend registry and the
``oracle`` backend), ``detections_file`` (``detections.jsonl``, ``needletrack detect``'s record).
"""

"""Scoring against ground truth, results and reports: ``needletrack eval`` and ``needletrack
results``, the graphs they run, the live graph's speed. May import every package above it in
docs/architecture.md's table (not ``bench``, ``robustness`` or ``adapt``).

Modules (``python -m common.layout`` writes this list from their docstrings):

- ``cli``: ``needletrack eval --dataset DIR [--detector learned|classical|oracle] [--out OUTDIR]``
- ``collect``: The evaluation of a run: the messages a graph published (``Collected``), scored
  against the truth (``evaluate`` -> ``Evaluation``) and summed up per keypoint and per method
  (``keypoint_table``, ``pose_table``).
- ``graph_speed``: The live pipeline's speed, end to end (``needletrack bench graph``, ``needletrack
  eval --bench``, the soak and the fuzz): the graph run, each stream's arrival times recorded
  (``Recorder``), and its throughput, latency per stage and each node's CPU measured (``measure``)
  and printed (``report``).
- ``metrics``: Errors against ground truth: statistics, which frames count, pose, NEES, keypoint and
  3D-point errors.
- ``moving``: The evaluation of moving takes (docs/tracking.md#evaluation): per-frame pose error by
  the share of the arc seen, and the needle in the jaws (``InHandPose``) against the true grasp.
- ``overlays``: An evaluation's overlays (``overlays/`` of ``common/evaluation/report.py``): per
  chosen frame (``select_overlay_frames``: the worst, a typical and the best), a crop of the left
  and right images around the needle: the true arc and keypoints in green (``common.palette``), each
  method's estimated arc in its colour, and the detector's keypoints as circles.
- ``pipeline_graph``: The standard pose pipeline as a graph, and running it with its source started
  last.
- ``recording``: The ``recorder`` node's file read back: each frame's refined pose and detections.
- ``replay_progress``: A graph run waited on while its replay's frames are shown as a bar:
  ``needletrack eval``'s and ``needletrack adapt``'s wait for their evaluator or recorder.
- ``report``: What people look at after an evaluation: ``report.md``, ``error_vs_distance.png``,
  ``nees.png``, ``overlays/``, ``per_frame.csv`` and ``results.json``, written from a
  ``common.evaluation.collect.Collected``; for moving takes also ``tracking.png`` and
  ``tracking.mp4``.
- ``results``: ``results.json``: what ``needletrack eval`` writes (``build_results``), its checker
  (``check_results``) and the JSON conversion of numpy values (``to_jsonable``).
- ``results_page``: ``needletrack results``: every figure of ``docs/results.md`` from one source,
  the ``results.json`` that ``needletrack eval`` writes.
- ``take_video``: ``tracking.mp4``: the moving take that ``tracking.png`` shows
  (``moving.shown_take``) as a video, written from a run's ``Collected`` poses
  (docs/tracking.md#evaluation).
- ``timing``: Timing of a run: latency and throughput of the final method, per-node times, and the
  CPU time of processes (Linux ``/proc``).
- ``tracker_replay``: The tracker replayed offline on a run's refined poses: tracker work without
  the detectors.
- ``withheld``: The frames whose one camera was withheld (``needletrack eval --withhold``): the
  tracked pose there, against the frames both cameras saw (docs/tracking.md#one-camera).
"""

"""Evaluation and benchmarks. May import every other package of ``common``.

``metrics`` (errors, NEES, which frames count), ``collect`` (a run's messages scored),
``results`` (``results.json``), ``timing``, ``results_page`` (``needletrack results``),
``report`` (tables and figures), ``overlays`` (the frames drawn), ``take_video`` (a
moving take's video), ``cli`` (the
``needletrack eval`` command), ``pipeline_graph`` (the graph an evaluation runs), ``folder_detections`` (the detector run
cold over a folder's images), ``detect_files`` (``needletrack detect``: the detector on a user's files), ``adapt`` (with
``adapt_run``, ``pseudo_labels``, ``adapt_calibration``: fitting without labels), ``finetune``
(with ``finetune_report``: fitting from hand labels, before and after); the
``needletrack bench`` benchmarks: ``graph_bench``, ``transport_bench``, ``sim_bench``,
``detector_bench``, ``refine_bench``, ``geometry_bench``, ``ros_bench`` (``ros-bag``, ``ros-live``), ``fuzz`` (with ``fuzz_payloads``, ``fuzz_ros``).
"""

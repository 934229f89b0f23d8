"""needletrack's library: everything that computes, usable without any process or network.

Packages, each importing only those listed before it (``nodes/`` wires them to Zenoh):

- ``geometry``: poses, cameras, the needle, ECM kinematics, PnP, triangulation, fusion, the dense
  refinement. Pure NumPy/OpenCV.
- ``runtime``: nodes, messages, graphs, the launcher and the graph tools. No geometry.
- ``data``: the dataset folder format (``docs/dataset.md``): read, write, check.
- ``sim``: the two renderers and the dataset generators, and the ``dataset`` command.
- ``detector``: the keypoint network, its training, inference and the detector backends.
- ``ros``: ROS bags in, live ROS 2 over Zenoh in and out, recordings as MCAP.
- ``viewer``: the live viewer's drawing, page and Rerun logging, and recordings.
- ``label``: hand labels in the browser (``needletrack label``).
- ``evaluation``: scoring against ground truth, results and reports, the pipeline graph.
- ``bench``: the benchmarks (``needletrack bench NAME``).
- ``robustness``: the fuzzers, the intruder check and the soak.
- ``adapt``: the detector on a user's footage: ``detect``, ``adapt``, ``finetune``.

``cli`` is the one entry point (``needletrack COMMAND``).
"""

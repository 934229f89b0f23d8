"""The graph under hostile and unlucky input: the fuzzers (``needletrack bench fuzz``,
``viewer-http``), the intruder check and the soak (``needletrack bench soak``). May import
``evaluation``, ``bench`` and every package above them.

Modules (``python -m common.layout`` writes this list from their docstrings):

- ``fuzz``: ``needletrack bench fuzz``: poison payloads into every input of every node of a graph,
  in process, the way the runtime hands them over (``decode`` with the input's type, then
  ``Node.deliver``), between frames of a clean stream.
- ``fuzz_payloads``: What ``needletrack bench fuzz`` sends (``common.robustness.fuzz``): the clean
  stream (the oracle's still needle seen by the default rig while the ECM yaws, through the
  library's nodes offline) and the poison payloads made from its messages (``KINDS``).
- ``fuzz_ros``: The fuzz's ROS 2 way in (``needletrack bench fuzz --node ros2``,
  ``common.robustness.fuzz``).
- ``http_fuzz``: The viewer page's HTTP server (``common.viewer.page``) under hostile and unlucky
  clients.
- ``intruder``: An intruder on a running graph: a local process without the run's credentials,
  optionally of another user (``--uid``), that tries to steer it (issue 32's probe).
- ``soak``: ``needletrack bench soak [--duration 600]``: the default graph (dataflow.yaml) for a
  long run, its camera replaced by a replay of a dataset folder looping at ``--rate`` (30 Hz).
"""

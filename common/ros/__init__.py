"""ROS without ROS: bags in (``bag``, ``convert``: the ``dataset from-bag`` command), live ROS 2
over Zenoh (``live``), recordings as MCAP (``record``). ``types`` registers message definitions
from text, ``images`` decodes sensor images, ``roles`` says what a message must be for its role, ``conventions`` and ``topicmap`` hold the AMBF and
dVRK presets and their frames, ``instruments`` the arms' topics and jaw
frames, ``synth`` writes the project's renders as bags (tests,
figures). Imports ``geometry``, ``data`` and ``runtime``; its benchmarks are
``common.bench.ros_bench``.
"""

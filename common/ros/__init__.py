"""ROS without ROS: bags in, live ROS 2 over Zenoh in and out, recordings as MCAP (docs/ros.md).
Imports ``geometry``, ``data`` and ``runtime``; its benchmarks are ``common.bench.ros_bench``.

Modules (``python -m common.layout`` writes this list from their docstrings):

- ``bag``: Stereo frames out of a ROS bag: ROS 1 ``.bag``, ROS 2 ``.db3`` or ``.mcap`` (a file or a
  bag directory), read with ``rosbags`` (no ROS installation).
- ``bagfuzz``: Damaged bag files for the readers (``needletrack bench fuzz --bags N``,
  tests/ros/test_bag_errors.py): a small synthetic stereo recording (an MCAP written the way
  ``needletrack record`` writes, zstd chunks, and a ROS 1 bag), then copies of it cut short, with a
  chunk's bytes overwritten, a CRC changed, a record length made absurd (4 GiB, 2^63), bit flips, or
  the summary and footer dropped (an unfinished recording).
- ``build``: Build ROS messages of a rosbags typestore: ``make(store, type, **fields)`` fills every
  field not given with its zero value (nested messages included), so a caller names only what it
  sets.
- ``cdr``: ROS message bytes <-> messages: the one place a ROS 1 or CDR (ROS 2) payload becomes a
  message (bags, live ROS 2 on Zenoh, recordings), with ``rosbags``' typestores.
- ``cli``: ``needletrack dataset from-bag|to-bag|distort``: ROS bags to dataset folders and back,
  and the distorted twin of a folder (docs/ros.md).
- ``conventions``: Frames, fixed transforms and units of the ROS sources (docs/ros.md states them
  all).
- ``convert``: ``needletrack dataset from-bag BAG --preset ambf|dvrk [--topics MAP.yaml] --out
  DIR``: a bag as a dataset folder (docs/dataset.md), so ``eval``, ``train`` and fine-tuning run on
  it.
- ``dds``: ROS 2 on its default middleware, DDS, spoken directly with Eclipse Cyclone DDS's Python
  binding (``cyclonedds``): no ROS installation, no bridge.
- ``images``: ROS image messages <-> (h, w, 3) uint8 BGR arrays.
- ``instruments``: The patient-side instruments of a ROS source: which topics carry each arm's
  tool-tip pose (``measured_cp``), its jaw angle (``jaw/measured_js``) and, optionally, its base's
  pose in world, and how they make the jaw frame of ``docs/dataset.md`` in world
  (docs/ros.md#instruments).
- ``live``: ROS 2 over Zenoh without ROS: the key expressions, attachments and liveliness tokens of
  the two ways ROS 2 data travels on Zenoh, with CDR payloads (de)serialised by ``rosbags``.
- ``reader``: Reading one bag's messages in order, for ``BagStereo`` (``common/ros/bag.py``):
  rosbags' ROS 1 and ROS 2 readers, with
- ``record``: ``needletrack record [-g GRAPH] --out FILE.mcap [KEYS...]``: a running graph's
  messages to MCAP with ROS 2 message schemas (``ros2msg`` schemas, CDR messages, profile ``ros2``),
  so a recording opens as a ROS 2 bag (``ros2 bag play``, rosbags) and in MCAP viewers, and plays
  back through the ``rosbag`` source (with the topic map written beside it,
  ``FILE.mcap.topics.yaml``).
- ``roles``: What a ROS message must be to serve its role in a topic map (image, camera_info,
  camera_state, ecm_joints, ecm_pose, needle_pose, camera_frame, instrument_jaw):
  ``message_problem`` says why one cannot, read from its fields without decoding pixels;
  ``pose_part`` and ``pose_of`` read the pose inside any pose-carrying message (metres after
  ``scale``).
- ``source``: What the ROS sources (``rosbag``, ``ros2``) publish for a ``StereoSample``: the
  images, the measured ECM pose, the ground truth, the instruments (``InstrumentState`` per arm) and
  the calibration, in the graph's messages (shared so the two sources agree to the byte).
- ``synth``: Bags in the robots' conventions from the project's own dataset folders (for tests,
  figures, and to check a converter end to end), and the distorted twin of a pinhole dataset.
- ``topicmap``: Topic maps: which topics of a bag (or a live ROS 2 system) carry what, and their
  conventions.
- ``types``: ROS message types without a ROS installation (the ``rosbags`` typestores).
"""

"""The dataset folder format (docs/dataset.md): read, written, checked; a user's own image and
video files as camera images. Imports ``geometry``, and ``runtime`` for the limits on what it
reads from disk and the messages a frame's truth travels in.

Modules (``python -m common.layout`` writes this list from their docstrings):

- ``check``: The dataset format's consistency checks (``docs/dataset.md``): the ground truth's
  projection, the joints' forward kinematics, the takes of a moving needle, the image files
  (``check_dataset``).
- ``cli``: ``needletrack dataset check|show|strip-truth``: validate a dataset folder against the
  spec and its ground truth, look at it (a contact sheet with the true keypoints), and copy it
  without its ground truth (what a user's recording holds).
- ``dataset``: Reader of the needle dataset format, version 1 (``docs/dataset.md``).
- ``instruments``: The patient-side instruments of a dataset frame (``instruments`` in
  ``docs/dataset.md``).
- ``media``: A user's own image and video files as a stream of camera images (``needletrack
  detect``).
- ``meta``: dataset.yaml of the needle dataset format (``docs/dataset.md``): its sections declared
  once (``MetaYaml``: each field with its parser and constraints), read by ``parse_meta`` into
  ``DatasetMeta``; ``DatasetError`` names the file, line and field of what breaks it.
- ``truth``: A frame's true poses from its ground truth (``GroundTruth``): the endoscope's
  ``T_world_ecm`` and the needle's ``T_ecm_needle``, 4x4, metres.
- ``values``: The value parsers of the dataset reader: each takes a decoded JSON/YAML value and
  returns it checked and converted, or raises ``BadValue`` with the reason (the caller adds the
  file, line and field, see ``common.data.dataset.DatasetError``).
- ``withhold``: One camera's images withheld for a share of each take: a lens covered by an
  instrument, smoke, a camera lost (issue 56's "one camera is enough").
- ``writer``: Writing needle dataset folders (``docs/dataset.md``): ``DatasetWriter``, a folder
  staged and moved into place, a file replaced atomically, a copy without the ground truth, and
  resuming a generation cut short.
"""

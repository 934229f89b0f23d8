"""The names of the frames every part of the project shares (docs/architecture.md#conventions).

``CAMERAS``: the stereo endoscope's cameras, in the order every per-camera map and pair uses.
Imports nothing: every package may use it.
"""

CAMERAS = ("left", "right")
"""The stereo cameras: left first (OpenCV frames x right, y down, z forward; docs/dataset.md)."""

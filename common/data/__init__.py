"""The dataset folder format (docs/dataset.md): ``dataset`` reads folders, ``writer`` writes
them, ``check`` runs the format's consistency checks; ``values`` parses its values,
``instruments`` a frame's instruments;
``media`` a user's own image and video files as camera images (``needletrack detect``).
Imports ``geometry``, and ``runtime.limits`` for the limits on what it reads from disk."""

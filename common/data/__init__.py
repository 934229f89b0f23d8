"""The dataset folder format (docs/dataset.md): ``dataset`` reads, writes and checks folders;
``values`` parses its values, ``instruments`` a frame's instruments.
Imports ``geometry``, and ``runtime.limits`` for the limits on what it reads from disk."""

"""The dataset folder format (docs/dataset.md): ``dataset`` reads, writes and checks folders.
Imports ``geometry``, and ``runtime.limits`` for the limits on what it reads from disk."""

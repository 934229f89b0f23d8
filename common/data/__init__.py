"""The dataset folder format (docs/dataset.md): ``dataset`` reads, writes and checks folders.
Imports ``geometry`` only."""

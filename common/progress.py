"""Progress on stderr: ``progress_bar``, the one way a long loop shows how far it has got (tqdm).
A function that takes ``progress: bool`` passes it as ``show``; a command's ``--quiet`` turns it
off. Imports nothing of ``common``."""
from __future__ import annotations


def progress_bar(iterable=None, *, show: bool = True, desc: str = "", unit: str = "frame", total=None,
                 **options):
    """A bar over ``iterable`` (or counting to ``total`` by ``update(n)``), drawn on stderr when
    ``show``; the same object, silent, when not. ``options``: tqdm's (``initial``, ``leave``,
    ``smoothing``, ``dynamic_ncols``)."""
    from tqdm import tqdm
    return tqdm(iterable, total=total, desc=desc, unit=unit, disable=not show, **options)

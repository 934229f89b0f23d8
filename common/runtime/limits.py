"""Limits on input read from disk: a YAML loader with a node budget, and an image-file reader
that checks size and header before it reads or decodes (see docs/robustness.md).

- YAML: ``load_yaml`` refuses a document nested deeper than ``MAX_YAML_DEPTH``, composes it,
  counts its nodes with every alias expanded (a "billion laughs" document of 1.5 KB expands to
  10^9) and refuses one over ``MAX_YAML_NODES`` before anything walks or builds it.
- Images: ``read_image_file`` refuses a path that is not a regular file, a symlink that leaves
  its folder, an empty file or one over ``MAX_IMAGE_BYTES`` (checked with ``stat`` before
  reading), and a file whose PNG/JPEG header states another size than expected (checked before
  decoding, so a small PNG claiming 16000x16000 px is never inflated).
"""
from __future__ import annotations

import os
import stat
from typing import Any, Optional

import yaml

from common.errors import NeedletrackError

MAX_YAML_NODES = 100_000
"""Most YAML nodes (scalars, lists, maps; aliases counted as the nodes they expand to)."""

MAX_YAML_DEPTH = 100
"""Deepest nesting of lists and maps (PyYAML composes recursively: a deeper document would
exhaust Python's stack with a ``RecursionError``)."""

MAX_IMAGE_BYTES = int(os.environ.get("NEEDLETRACK_MAX_IMAGE_BYTES", 64 << 20))
"""Largest image file read (bytes; env ``NEEDLETRACK_MAX_IMAGE_BYTES``, default 64 MiB)."""


class InputLimitError(NeedletrackError, ValueError):
    """Input from disk that breaks a limit; the text names the file and what is wrong."""


def yaml_node_count(root, budget: int) -> int:
    """Nodes of a composed YAML document with aliases expanded; stops counting past ``budget``."""
    n, stack = 0, [root]
    while stack:
        node = stack.pop()
        n += 1
        if n > budget:
            return n
        if isinstance(node, yaml.MappingNode):
            for k, v in node.value:
                stack.extend((k, v))
        elif isinstance(node, yaml.SequenceNode):
            stack.extend(node.value)
    return n


def check_yaml_depth(text: str, where: str = "YAML", max_depth: int = MAX_YAML_DEPTH) -> None:
    """``InputLimitError`` when lists and maps in ``text`` nest deeper than ``max_depth`` (checked
    on the parser's events, which need no recursion); YAML errors propagate."""
    depth = 0
    for ev in yaml.parse(text, Loader=yaml.SafeLoader):
        if isinstance(ev, (yaml.SequenceStartEvent, yaml.MappingStartEvent)):
            depth += 1
            if depth > max_depth:
                m = ev.start_mark
                raise InputLimitError(f"{where}: line {m.line + 1}, column {m.column + 1}: lists and maps "
                                      f"nested deeper than {max_depth}: refused")
        elif isinstance(ev, (yaml.SequenceEndEvent, yaml.MappingEndEvent)):
            depth -= 1


def compose_yaml(text: str, where: str = "YAML", max_nodes: int = MAX_YAML_NODES):
    """The composed node tree of ``text`` (``yaml.compose``, safe), refused with
    ``InputLimitError`` when it nests deeper than ``MAX_YAML_DEPTH`` or expands to more than
    ``max_nodes`` nodes."""
    check_yaml_depth(text, where)
    root = yaml.compose(text, Loader=yaml.SafeLoader)
    if root is not None and yaml_node_count(root, max_nodes) > max_nodes:
        raise InputLimitError(f"{where}: expands to more than {max_nodes} YAML nodes (aliases "
                              f"counted as what they repeat): refused")
    return root


def load_yaml(text: str, where: str = "YAML", max_nodes: int = MAX_YAML_NODES) -> Any:
    """``yaml.safe_load`` with the node budget of ``compose_yaml``; YAML errors propagate."""
    root = compose_yaml(text, where, max_nodes)
    if root is None:
        return None
    loader = yaml.SafeLoader("")
    try:
        return loader.construct_document(root)
    finally:
        loader.dispose()


def describe_path(path: str) -> str:
    """What is at ``path`` when it is not a regular file: "does not exist", "is a directory",
    "is a FIFO (pipe)", ..."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return "does not exist" if not os.path.islink(path) else "is a broken symlink"
    except OSError as exc:
        return f"cannot be read ({exc.strerror})"
    mode = st.st_mode
    for test, what in ((stat.S_ISDIR, "is a directory"), (stat.S_ISFIFO, "is a FIFO (pipe)"),
                       (stat.S_ISSOCK, "is a socket"), (stat.S_ISCHR, "is a character device"),
                       (stat.S_ISBLK, "is a block device")):
        if test(mode):
            return what
    return "is not a regular file"


def inside(folder: str, rel: str) -> str:
    """``folder/rel`` if it resolves (symlinks followed) inside ``folder``; else InputLimitError."""
    path = os.path.join(folder, rel)
    root = os.path.realpath(folder)
    real = os.path.realpath(path)
    if os.path.commonpath([root, real]) != root:
        raise InputLimitError(f"{rel}: leads out of the folder {folder} (to {real}): refused")
    return path


def read_image_file(folder: str, rel: str, expect_size: Optional[tuple] = None,
                    max_bytes: Optional[int] = None) -> bytes:
    """The bytes of the PNG/JPEG image ``rel`` in ``folder``, after the checks of the module
    docstring (``expect_size``: (width, height) px the header must state)."""
    from common.runtime.messages import image_header_size
    max_bytes = MAX_IMAGE_BYTES if max_bytes is None else max_bytes
    path = inside(folder, rel)
    if not os.path.isfile(path):
        raise InputLimitError(f"{rel}: image file {describe_path(path)}")
    size = os.path.getsize(path)
    if size == 0:
        raise InputLimitError(f"{rel}: image file is empty (0 bytes)")
    if size > max_bytes:
        raise InputLimitError(f"{rel}: image file is {size} bytes, over the limit of {max_bytes} "
                              f"(NEEDLETRACK_MAX_IMAGE_BYTES)")
    with open(path, "rb") as f:
        data = f.read(max_bytes + 1)
    if len(data) > max_bytes:         # it grew since stat
        raise InputLimitError(f"{rel}: image file over the limit of {max_bytes} bytes")
    hs = image_header_size(data)
    if hs is None:
        raise InputLimitError(f"{rel}: not a readable PNG or JPEG image (no valid header; {len(data)} bytes)")
    if expect_size is not None and tuple(hs) != tuple(expect_size):
        raise InputLimitError(f"{rel}: the image header says {hs[0]}x{hs[1]}, expected "
                              f"{expect_size[0]}x{expect_size[1]} (dataset.yaml image_size); not decoded")
    return data

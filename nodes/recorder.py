"""Recorder: writes the poses and keypoints a graph produces to a JSON-lines file, for a later
step that reads them without the graph (``needletrack adapt``'s pseudo-labels).

Each line is one message: ``{"kind": "pose", ...PoseEstimate fields}``, ``{"kind": "one_camera",
...}`` (a pose fitted to one camera's view: the refine node's ``one_camera`` output) or
``{"kind": "keypoints", ...Keypoints fields}`` (arrays as nested lists, NaN as null). After the
source's EndOfStream and ``drain_s`` seconds without a message it writes
``{"kind": "end", "frames": N}`` and exits 0; a file without that line is an unfinished run.

Params: ``out`` (the file, required; replaced), ``drain_s`` (default 3).
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, fields

from common.evaluation.results import to_jsonable
from common.constraints import required
from common.runtime.messages import EndOfStream, Keypoints, PoseEstimate
from common.runtime.node import Node, NodeError, run


def message_record(kind: str, msg) -> dict:
    """One line of the file: the message's fields, JSON-ready."""
    return {"kind": kind, **{f.name: to_jsonable(getattr(msg, f.name)) for f in fields(msg)}}


class RecorderNode(Node):
    """Poses and keypoints in, one JSON line each out to ``params.out``."""

    INPUTS = {"pose": PoseEstimate, "one_camera": PoseEstimate, "left": Keypoints, "right": Keypoints,
              "eos": EndOfStream}
    OUTPUTS = ()
    KEEP_ALL = tuple(INPUTS)

    @dataclass
    class Params:
        out: required("the JSON-lines file") = ""
        drain_s: float = 3.0

    def setup(self):
        try:
            self.file = open(self.p.out, "w", encoding="utf-8")
        except OSError as exc:
            raise NodeError(f"params.out {self.p.out}: cannot write ({exc.strerror})") from None
        self._eos: EndOfStream | None = None
        self._last = time.monotonic()

    def _write(self, kind: str, msg) -> None:
        self._last = time.monotonic()
        self.file.write(json.dumps(message_record(kind, msg), separators=(",", ":")) + "\n")

    def on_pose(self, msg: PoseEstimate):
        self._write("pose", msg)

    def on_one_camera(self, msg: PoseEstimate):
        self._write("one_camera", msg)

    def on_left(self, msg: Keypoints):
        self._write("keypoints", msg)

    def on_right(self, msg: Keypoints):
        self._write("keypoints", msg)

    def on_eos(self, msg: EndOfStream):
        self._last = time.monotonic()
        self._eos = msg

    def step(self):
        time.sleep(0.02)
        if self._eos is None or time.monotonic() - self._last < self.p.drain_s:
            return True
        self.file.write(json.dumps({"kind": "end", "frames": int(self._eos.frames)}) + "\n")
        self.file.close()
        self.log.info("recorded %d frames' outputs to %s", self._eos.frames, self.p.out)
        return False


NODE = RecorderNode
if __name__ == "__main__":
    run(NODE)

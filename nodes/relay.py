"""Test/demo node: republishes every message of ``in`` on ``out`` (any message type).

params: ``work_ms`` (default 0) simulated processing time per message.
"""
import time
from dataclasses import dataclass

from common.runtime.node import Node, run


class Relay(Node):
    """Forwards each input message unchanged."""

    INPUTS = {"in": None}
    OUTPUTS = ("out",)
    KEEP_ALL = ("in",)

    @dataclass
    class Params:
        work_ms: float = 0.0     # simulated work per message

    def setup(self):
        self.work_s = self.p.work_ms / 1e3

    def on_in(self, msg):
        if self.work_s:
            time.sleep(self.work_s)
        self.publish("out", msg)


NODE = Relay
if __name__ == "__main__":
    run(NODE)

"""Timing of a run: latency and throughput of the final method, per-node times, and the CPU
time of processes (Linux ``/proc``)."""
from __future__ import annotations

from typing import TYPE_CHECKING, Optional


from common.evaluation.metrics import percentile
from common.methods import last_stage

if TYPE_CHECKING:
    from common.evaluation.collect import Collected


def process_cpu_seconds(pid: int) -> Optional[float]:
    """CPU time (user + system, s) process ``pid`` has used, from /proc; None if unknown."""
    import os
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return None


def cpu_steal_seconds() -> Optional[float]:
    """CPU time (s, summed over CPUs) the hypervisor has given other guests so far (``steal`` in
    /proc/stat): on a shared virtual machine, what makes a slow minute; None if unknown."""
    import os
    try:
        with open("/proc/stat") as f:
            fields = f.readline().split()
        return int(fields[8]) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


def timing_summary(col: Collected, final_method: Optional[str] = None) -> dict:
    """``{"throughput_hz", "latency_ms": {"p50", "p99"}, "per_node_ms": {node: p50}}``.

    Latency: wall-clock arrival of the ``final_method`` pose at the evaluator minus the time the
    source published the frame: its truth's arrival where it came (an evaluation's replay stamps
    frames with their recorded timing), else its ``stamp_ns``. Throughput: poses of the final
    method per second, from the first published frame to the last pose.
    """
    if final_method is None:
        final_method = last_stage(m for m in col.poses if col.poses.get(m))
    lat, thr = [], None
    if final_method is not None:
        poses, arr = col.poses[final_method], col.arrivals_ns[final_method]
        sent = {s: col.truth_arrivals_ns.get(s, p.stamp_ns) for s, p in poses.items()}
        lat = [(arr[s] - sent[s]) / 1e6 for s in poses]
        first = min(sent.values())
        span = (max(arr.values()) - first) / 1e9
        thr = len(poses) / span if span > 0 else None
    return {"throughput_hz": thr,
            "latency_ms": {"p50": percentile(lat, 50), "p99": percentile(lat, 99)},
            "per_node_ms": dict(sorted(col.node_ms.items())),
            "per_node_cpu_ms_per_frame": dict(sorted(col.node_cpu_ms.items())),
            "final_method": final_method}

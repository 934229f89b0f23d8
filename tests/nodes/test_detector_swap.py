"""Issue 5, deliverable 6: the detector's backend swapped at runtime (oracle -> classical ->
learned -> oracle) through the runtime's make-before-break swap, in a launched graph (real
processes, Zenoh on loopback), while frames flow: every backend publishes after its swap, no
frame seq is published twice, and at most one frame is missing across each handover."""
import pytest
import os
import signal

import numpy as np

from common.data.check import project_keypoints
from common.data.dataset import DatasetMeta, Frame
from common.data.writer import DatasetWriter
from common.geometry.camera import StereoRig
from common.geometry.needle import NeedleModel
from common.geometry.transforms import make_T, rotvec_to_R
from common.runtime.messages import Keypoints
from common.sim.randomise import default_arm

pytestmark = pytest.mark.graph

W, H = 160, 90           # tiny images: the swap is under test, not the detectors' accuracy
RATE_HZ = 10             # low enough for every backend to keep up on two busy cores
ORDER = ("oracle", "classical", "learned", "oracle")
BACKEND_PARAMS = {"oracle": {"noise_px": 0.5}, "classical": {}, "learned": {"device": "cpu", "threads": 1}}
ALL_PARAMS = {k for p in BACKEND_PARAMS.values() for k in p}
AFTER_SWAP = 5           # messages per camera each backend must publish after its swap


def _dataset(folder, n: int = 20) -> None:
    """A small dataset with ground truth (the oracle needs it) and plain gradient images."""
    meta = DatasetMeta((W, H), StereoRig.default(W, H), NeedleModel(), default_arm(), "detector swap test")
    ramp = np.linspace(60, 160, W, dtype=np.uint8)[None, :, None]
    with DatasetWriter(folder, meta) as wr:
        for i in range(n):
            img = np.broadcast_to(ramp + np.uint8(i), (H, W, 3)).copy()
            paths = wr.write_images(i, {"left": img, "right": img})
            q = np.array([0.0, 0.002 * i, 0.12, 0.0])
            T_we = meta.arm.T_world_ecm(q)
            T_wn = T_we @ make_T(rotvec_to_R([2.9, 0.1, 0.0]), [0.0, 0.0, -0.13])
            wr.append(Frame(index=i, stamp_ns=i * 100_000_000, left=paths["left"], right=paths["right"],
                            ecm_joints=q, T_world_ecm=T_we, T_world_needle=T_wn,
                            keypoints=project_keypoints(meta, T_we, T_wn)))


def handovers(msgs: list) -> list:
    """``[(seq before, seq after, backend before, backend after)]`` at every change of the
    ``detector`` field, in seq order."""
    msgs = sorted(msgs, key=lambda m: m.seq)
    return [(a.seq, b.seq, a.detector, b.detector) for a, b in zip(msgs, msgs[1:]) if a.detector != b.detector]


def _graph(folder, backend: str = "oracle") -> dict:
    """replay (looping at RATE_HZ) -> detector (both cameras, one process)."""
    return {"nodes": [
        {"id": "camera", "module": "replay", "outputs": ["left", "right", "joints", "truth", "calib", "eos"],
         "params": {"path": str(folder), "rate": RATE_HZ, "loop": True}},
        {"id": "detector", "module": "detector",
         "params": {"backend": backend, **BACKEND_PARAMS[backend]},
         "inputs": {"left": "camera/left", "right": "camera/right", "truth": "camera/truth",
                    "calib": "camera/calib"},
         "outputs": ["left", "right"]}]}


def test_detector_backend_swaps_at_runtime_with_at_most_one_frame_missing(run_graph, tmp_path):
    _dataset(tmp_path / "ds")
    g = run_graph(_graph(tmp_path / "ds", ORDER[0]), timeout=60)
    subs = {cam: g.subscribe(f"detector/{cam}", Keypoints) for cam in ("left", "right")}
    for sub in subs.values():
        sub.wait(AFTER_SWAP, 30, where=lambda m: m.detector == ORDER[0])
    pids = [g.pids()["detector"]]
    summaries = []
    for backend in ORDER[1:]:
        # the new backend's outputs come after everything published before its swap
        marks = {cam: max(m.seq for m in sub.messages) for cam, sub in subs.items()}
        # the old backend's params go, the new one's come (each backend checks its own)
        res = g.swap("detector", backend=backend, unset=[k for k in ALL_PARAMS if k not in BACKEND_PARAMS[backend]],
                     timeout=90, **BACKEND_PARAMS[backend])
        assert res.returncode == 0, res.stdout + res.stderr + g.log()[-4000:]
        summaries.append(res.stdout.strip())
        for cam, sub in subs.items():
            sub.wait(AFTER_SWAP, 30, where=lambda m, b=backend, s=marks[cam]: m.detector == b and m.seq > s)
        pids.append(g.pids()["detector"])
    assert len(set(pids)) == len(pids), f"every swap runs a new process: {pids}"

    for cam, sub in subs.items():
        msgs = list(sub.messages)
        seqs = [m.seq for m in msgs]
        dupes = sorted({s for s in seqs if seqs.count(s) > 1})
        assert not dupes, f"{cam}: frames published twice across the swaps: {dupes}"
        assert all(m.camera == cam for m in msgs)
        hand = handovers(msgs)
        # each backend in turn, each handed over exactly once, in the order swapped
        assert [(a, b) for _, _, a, b in hand] == list(zip(ORDER, ORDER[1:])), f"{cam}: {hand}\n{summaries}"
        for before, after, a, b in hand:
            assert after - before <= 2, f"{cam}: {a} -> {b} skipped frames {before + 1}..{after - 1}"
        print(f"{cam} handovers (last seq, first seq, from, to): {hand}")
    st = g.wait_stats("detector", lambda st: st.pid == pids[-1])
    assert st.counters["handler_errors"] == 0 and st.counters["decode_errors"] == 0
    assert st.counters["state"] == "active"
    print("\n".join(summaries))


def test_a_failed_backend_swap_leaves_the_running_backend_in_place_for_good(run_graph, tmp_path):
    """A swap to a backend that cannot start (a missing weight file) fails; the running backend
    keeps publishing, and a later restart of the node (kill -9) still runs that backend, not the
    refused one."""
    _dataset(tmp_path / "ds")
    g = run_graph(_graph(tmp_path / "ds", "oracle"), timeout=60)
    g.collect("detector/left", 3, timeout=30, expect=Keypoints)
    pid = g.pids()["detector"]
    res = g.swap("detector", backend="learned", weights=str(tmp_path / "missing.pt"), unset=["noise_px"], timeout=90)
    assert res.returncode == 1 and "before taking over" in res.stderr, res.stdout + res.stderr
    g.wait_log("missing.pt")                             # the node said which file it could not load
    assert g.pids()["detector"] == pid
    msgs = g.collect("detector/left", 3, timeout=20, expect=Keypoints)
    assert {m.detector for m in msgs} == {"oracle"}
    os.kill(pid, signal.SIGKILL)
    g.wait_stats("detector", lambda st: st.pid != pid, timeout=30)
    msgs = g.collect("detector/left", 3, timeout=20, expect=Keypoints)
    assert {m.detector for m in msgs} == {"oracle"}, g.log()[-4000:]
    assert {r["node"]: r["restarts"] for r in g.status()["nodes"]}["detector"] == 1


def test_a_slow_backend_hands_over_only_once_its_successor_covers_the_next_frame(run_graph):
    """A slow old backend lags the frames: it may still be on frame L while the new process already
    holds outputs from S0 > L + 1 on. The handover waits until the old one has published up to
    S0 - 1, so the new backend continues exactly at the frame after the old one's last output."""
    g = run_graph({"nodes": [
        {"id": "count", "module": "counter", "params": {"rate_hz": 10}},
        {"id": "det", "module": "tagger", "params": {"tag": "slow", "delay_s": 0.25}, "inputs": {"in": "count/out"}}]})
    sub = g.subscribe("det/out", Keypoints)
    sub.wait(3, 15)
    for tag, delay in (("fast", 0.0), ("slow", 0.25), ("fast", 0.0)):
        mark = max(m.seq for m in sub.messages)
        res = g.swap("det", tag=tag, delay_s=delay)
        assert res.returncode == 0, res.stdout + res.stderr
        sub.wait(3, 15, where=lambda m, t=tag, s=mark: m.detector == t and m.seq > s)
    msgs = sorted(sub.messages, key=lambda m: m.seq)
    seqs = [m.seq for m in msgs]
    assert len(set(seqs)) == len(seqs), "a frame was published twice"
    hand = handovers(msgs)
    assert [(a, b) for _, _, a, b in hand] == [("slow", "fast"), ("fast", "slow"), ("slow", "fast")], hand
    slow_to_fast = [(x, y) for x, y, a, _ in hand if a == "slow"]
    assert all(y == x + 1 for x, y in slow_to_fast), f"frames lost at a handover from the slow backend: {hand}"

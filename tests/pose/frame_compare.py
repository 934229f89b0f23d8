"""Before/after check of a refactor on any rendered folder, frame by frame, without Zenoh: the
tree on ``PYTHONPATH`` (this file may live in another) plays a dataset folder offline and drives
the pose nodes over it, as ``test_frame_outputs.py`` does over its recorded inputs; two trees'
files are then compared message by message, every field bitwise (arrays as their bytes).

    PYTHONPATH=TREE python tests/pose/frame_compare.py inputs DATASET oracle|learned IN.msgpack
    PYTHONPATH=TREE python tests/pose/frame_compare.py outputs IN.msgpack OUT.msgpack
    python tests/pose/frame_compare.py compare A.msgpack B.msgpack      # exit 1 on a difference
    PYTHONPATH=TREE python tests/pose/frame_compare.py eval EVAL_ARGS   # needletrack eval, recorded
    python tests/pose/frame_compare.py compare-eval OUT_A OUT_B         # two `needletrack eval` folders

``inputs``: the ``replay``, ``ecm`` and ``detector`` nodes offline (the oracle: 1 px noise, seed
0, on the truth; learned: the shipped weights on the images, stride 1), their messages in the
order published, each stamped ``seq / 30`` s and of one stream (``epoch`` 1), where ``needletrack
eval`` stamps them with the wall clock: the ``tracked`` poses, whose motion model steps by the
stamps, then vary from run to run there but not here. ``outputs``: ``test_frame_outputs.run``
over them in each of its orderings and ``BEYOND_REPLAY``. ``compare``: fields that only B's
messages carry (added in B's code) are listed, not compared. ``eval``: ``needletrack eval`` (its arguments, ``--out OUT``
among them) with a ``recorder`` node on every pose output and on the keypoints, writing
``OUT/rec/<method>.jsonl`` (every field at full precision). ``compare-eval``: those recordings
message by message but for ``stamp_ns`` and ``epoch`` (the wall clock, the stream's random id),
``per_frame.csv`` cell by cell and ``results.json`` but for ``timing``, ``bench`` and ``dataset``. docs/evaluation.md
(#checking-that-a-refactor-keeps-behaviour) has the check of issue 57.
"""
from __future__ import annotations

import csv
import json
import sys
from collections import Counter, defaultdict
from pathlib import Path

import msgpack

STAMP0_NS, FRAME_NS = 1_700_000_000_000_000_000, 33_333_333
EVAL_UNCOMPARED = ("timing", "bench", "dataset")


def record_inputs(dataset: str, detector: str) -> list:
    """The events ``test_frame_outputs.run`` takes: ``(source, type name, encoded message)``."""
    from common.runtime.messages import encode
    from nodes.detector import DetectorNode
    from nodes.ecm import EcmNode
    from nodes.replay import ReplayNode
    replay = ReplayNode.offline({"path": dataset, "rate": "max"})
    ecm = EcmNode.offline({}, wired=["joints", "calib", "measured"])
    if detector == "oracle":
        det = DetectorNode.offline({"backend": "oracle", "noise_px": 1.0, "seed": 0}, wired=["truth", "calib"])
    elif detector == "learned":
        det = DetectorNode.offline({"backend": "learned", "stride": 1}, wired=["left", "right", "calib"])
    else:
        raise ValueError(f"detector {detector!r}: oracle or learned")
    events: list = []

    def feed(node, inp: str, msg) -> None:
        getattr(node, f"on_{inp}")(msg)
        for out, m in node.published:
            name = "ecm" if node is ecm else out
            events.append((name, type(m).__name__, encode(m)))
        node.published.clear()

    def emit(name: str, msg) -> None:
        events.append((name, type(msg).__name__, encode(msg)))

    more, calib_sent = True, False
    while more:
        more = replay.step()
        published, replay.published[:] = list(replay.published), []
        for out, m in published:
            m = getattr(m, "msg", m)                       # a prepared image: its message
            if hasattr(m, "seq") and hasattr(m, "stamp_ns"):
                m.stamp_ns = STAMP0_NS + FRAME_NS * int(m.seq)
            if getattr(m, "epoch", None) is not None:
                m.epoch = 1
            if out == "calib":
                if calib_sent:
                    continue                               # once a second live: once here
                calib_sent, m.stamp_ns = True, STAMP0_NS
                emit("calib", m)
                feed(ecm, "calib", m)
                feed(det, "calib", m)
            elif out in ("joints", "measured"):
                feed(ecm, out, m)
            elif out in ("truth", "instruments"):
                emit(out, m)
                if out == "truth" and detector == "oracle":
                    feed(det, "truth", m)
            elif out in ("left", "right") and detector != "oracle":
                feed(det, out, m)
            elif out == "eos":
                m.stamp_ns = STAMP0_NS + FRAME_NS * (len(replay.frames) + 1)
                emit("eos", m)
    return events


BEYOND_REPLAY = {"refine/pose>tracker": 20, "refine/no_pose>tracker": 0}
"""One more ordering: the refined poses reach the tracker 20 frames late, its notices at once (in
``needletrack eval`` the two come through separate queues): past the tracker's ``replay`` window,
so poses are dropped (``late_pose``) and frames coasted."""


def drive(events: list) -> dict:
    """Per ordering (``test_frame_outputs.ORDERS`` and ``beyond_replay``): per node its outputs
    and counters."""
    sys.path.insert(0, str(Path(__file__).parent))
    import test_frame_outputs as tfo
    orders = {**tfo.ORDERS, "beyond_replay": BEYOND_REPLAY}
    return {order: tfo.run(events, delays) for order, delays in orders.items()}


def _body(raw: bytes):
    d = msgpack.unpackb(raw, raw=False, strict_map_key=False, ext_hook=lambda c, b: ("ext", c, bytes(b)))
    return d["schema"], d["body"]


def message_differences(a, b) -> tuple[int, list, dict]:
    """(messages compared, differences, {schema.field: Counter of values} of the fields only B has)."""
    bad: list = []
    added: dict = defaultdict(Counter)

    def lists(la, lb, where):
        if [n for n, _ in la] != [n for n, _ in lb]:
            bad.append(f"{where}: outputs {dict(Counter(n for n, _ in la))} != {dict(Counter(n for n, _ in lb))}")
            return 0
        for (name, ra), (_, rb) in zip(la, lb):
            (sa, ba), (sb, bb) = _body(ra), _body(rb)
            if sa != sb:
                bad.append(f"{where} {name}: schema {sa} != {sb}")
                continue
            for k in bb.keys() - ba.keys():
                added[f"{sa}.{k}"][repr(bb[k])[:40]] += 1
            bad.extend(f"{where} {name} seq {ba.get('seq')} {k}" for k in ba if ba[k] != bb.get(k, KeyError))
        return len(la)

    if isinstance(a, list):
        return lists([(e[0], e[2]) for e in a], [(e[0], e[2]) for e in b], "events"), bad, dict(added)
    n = 0
    for order in a:
        for nid in a[order]:
            n += lists(a[order][nid]["out"], b[order][nid]["out"], f"{order} {nid}")
            if a[order][nid]["counters"] != b[order][nid]["counters"]:
                bad.append(f"{order} {nid} counters: {a[order][nid]['counters']} != {b[order][nid]['counters']}")
    return n, bad, dict(added)


def _json_paths(a, b, path=""):
    if isinstance(a, dict) and isinstance(b, dict):
        return [p for k in sorted(set(a) | set(b)) for p in _json_paths(a.get(k), b.get(k), f"{path}.{k}")]
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        return [p for i, (x, y) in enumerate(zip(a, b)) for p in _json_paths(x, y, f"{path}[{i}]")]
    return [] if a == b else [path]


def recorded_eval(argv: list[str]) -> int:
    """``needletrack eval argv`` with recorders (module docstring); its exit status."""
    import common.evaluation.pipeline_graph as pg
    from common.evaluation.cli import main as eval_main
    from common.methods import POSE_OUTPUTS
    rec = Path(argv[argv.index("--out") + 1]).resolve() / "rec"
    rec.mkdir(parents=True, exist_ok=True)
    recorders: list = []
    graph, wait = pg.pipeline_graph, pg.GraphRun.wait

    def with_recorders(*a, **k):
        doc = graph(*a, **k)
        ids = {n["id"] for n in doc["nodes"]}
        kp = pg.keypoint_sources(k.get("split_detector", False))
        taps = {m: {"pose": o} for m, o in POSE_OUTPUTS.items() if o.split("/")[0] in ids}
        for name, inputs in {**taps, "keypoints": dict(kp)}.items():
            recorders.append(f"rec_{name}")
            doc["nodes"].append({"id": f"rec_{name}", "module": "recorder", "restart": "never",
                                 "params": {"out": str(rec / f"{name}.jsonl"), "drain_s": 2.0},
                                 "inputs": {**inputs, "eos": "replay/eos"}})
        return doc

    pg.pipeline_graph = with_recorders
    pg.GraphRun.wait = lambda run, until, timeout: wait(run, list(until) + recorders, timeout)
    return eval_main(argv)


def _recorded(path: Path) -> dict:
    """A recording's messages by (kind, seq, camera), less the fields set by the clock."""
    out: dict = {}
    for line in path.read_text().splitlines():
        r = json.loads(line)
        if r["kind"] != "end":
            key = (r["kind"], r["seq"], r.get("camera"))
            out.setdefault(key, []).append({k: v for k, v in r.items() if k not in ("stamp_ns", "epoch")})
    return out


def eval_differences(out_a: Path, out_b: Path) -> list[str]:
    """Recorded messages (``rec/<method>.jsonl`` seq: fields), ``per_frame.csv`` cells (``seq
    column``) and ``results.json`` fields that differ; fields only B's messages carry are not
    compared."""
    bad = []
    for fa in sorted((out_a / "rec").glob("*.jsonl")):
        ra, rb = _recorded(fa), _recorded(out_b / "rec" / fa.name)
        for key in sorted(set(ra) | set(rb), key=str):
            ma, mb = ra.get(key, []), rb.get(key, [])
            if len(ma) != len(mb):
                bad.append(f"rec/{fa.name} {key[0]} seq {key[1]}: {len(ma)} != {len(mb)} messages")
                continue
            fields = sorted({k for x, y in zip(ma, mb) for k in x if x[k] != y.get(k, KeyError)})
            if fields:
                bad.append(f"rec/{fa.name} {key[0]} seq {key[1]}" + (f" {key[2]}" if key[2] else "")
                           + f": {', '.join(fields)}")
    rows_a = list(csv.DictReader(open(out_a / "per_frame.csv")))
    rows_b = list(csv.DictReader(open(out_b / "per_frame.csv")))
    if len(rows_a) != len(rows_b):
        bad.append(f"per_frame.csv: {len(rows_a)} != {len(rows_b)} rows")
    bad += [f"per_frame.csv seq {ra['seq']} {c}: {ra[c]} != {rb.get(c)}"
            for ra, rb in zip(rows_a, rows_b) for c in ra if ra[c] != rb.get(c)]
    ja, jb = (json.loads((o / "results.json").read_text()) for o in (out_a, out_b))
    bad += [f"results.json {p}" for p in _json_paths(ja, jb) if p.split(".")[1].split("[")[0] not in EVAL_UNCOMPARED]
    return bad


def main(argv: list[str]) -> int:
    cmd, *args = argv
    if cmd == "inputs":
        dataset, detector, out = args
        events = record_inputs(dataset, detector)
        Path(out).write_bytes(msgpack.packb(events))
        print(f"{out}: {len(events)} messages, {dict(Counter(e[0] for e in events))}")
    elif cmd == "outputs":
        events = msgpack.unpackb(Path(args[0]).read_bytes(), raw=False, strict_map_key=False)
        res = drive(events)
        Path(args[1]).write_bytes(msgpack.packb(res))
        print(f"{args[1]}:", {o: {nid: len(v["out"]) for nid, v in r.items()} for o, r in res.items()})
    elif cmd == "compare":
        a, b = (msgpack.unpackb(Path(p).read_bytes(), raw=False, strict_map_key=False) for p in args)
        n, bad, added = message_differences(a, b)
        print(f"{n} messages compared, {len(bad)} differ" + "".join(f"\n  {x}" for x in bad))
        print("fields only in B (not compared):", {k: dict(v) for k, v in added.items()} or "none")
        return 1 if bad else 0
    elif cmd == "eval":
        return recorded_eval(args)
    elif cmd == "compare-eval":
        bad = eval_differences(Path(args[0]), Path(args[1]))
        print(f"{len(bad)} differences" + "".join(f"\n  {x}" for x in bad))
        return 1 if bad else 0
    else:
        print(__doc__, file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

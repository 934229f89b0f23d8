"""Joining a node's inputs by frame seq (common/runtime/pairing.py: SeqJoin)."""
from common.runtime.pairing import SeqCache, SeqJoin


def test_an_item_waits_for_its_frame_at_most_max_wait_frames():
    have = set()
    join = SeqJoin(max_wait=3)
    join.hold(5, "a")
    join.hold(6, "b")
    ready = lambda seq, _: seq in have     # noqa: E731
    assert join.due(ready) == [] and len(join) == 2
    have.add(6)                            # out of order: b's frame is complete first
    assert join.due(ready) == [("b", True)] and list(join) == ["a"]
    join.see(7)
    assert join.due(ready) == []
    join.see(8)                            # 3 frames behind the newest: goes without its inputs
    assert join.due(ready) == [("a", False)] and len(join) == 0


def test_in_order_an_item_not_due_holds_back_the_later_ones():
    have = {2}
    join = SeqJoin(max_wait=5, in_order=True)
    for seq in (2, 1, 3):                  # held in any order, released by seq
        join.hold(seq, seq)
    ready = lambda seq, _: seq in have     # noqa: E731
    assert join.due(ready) == []           # 1 is not in: 2 waits behind it
    have.add(1)
    assert join.due(ready) == [(1, True), (2, True)] and list(join) == [3]
    join.see(8)
    assert join.due(ready) == [(3, False)]


def test_drop_and_reset():
    join = SeqJoin(max_wait=2)
    for seq, cam in ((1, "left"), (1, "right"), (2, "left")):
        join.hold(seq, (seq, cam))
    assert join.drop(lambda _, item: item[1] == "left") == [(1, "left"), (2, "left")]
    assert list(join) == [(1, "right")]
    assert join.reset() == [(1, "right")] and join.newest == -1 and len(join) == 0
    join.hold(0, "x")                      # a new stream from seq 0 is not stale
    assert join.due(lambda *_: False) == []


def test_seq_cache_keeps_the_newest():
    c = SeqCache(2)
    for s in range(4):
        c.put(s, s * 10)
    assert list(c.items()) == [(2, 20), (3, 30)]

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


def test_a_frame_join_names_what_a_frame_went_on_without():
    """FrameJoin: the waits declared once; a frame released late says which inputs it lacked,
    and one that lacked a needed input is dropped, counted only for that."""
    from common.runtime.pairing import FrameJoin, Wait
    ecm, truth = set(), set()
    join = FrameJoin([Wait("ecm", lambda s, _: s in ecm, needed=True, missing="no_ecm"),
                      Wait("truth", lambda s, _: s in truth, missing="no_truth")], max_wait=2, in_order=True)
    for seq in (1, 2, 3):
        join.hold(seq, f"pose{seq}")
    ecm.update({1, 2})
    truth.add(1)
    r = join.due()
    assert [(x.item, x.complete) for x in r] == [("pose1", True)] and len(join) == 2
    join.see(4)                            # 2 is 2 frames behind: goes on without its truth
    (r,) = join.due()
    assert (r.item, r.missing, r.dropped, r.counters) == ("pose2", ("truth",), False, ("no_truth",))
    join.see(5)                            # 3 has neither: dropped, counted for the ECM pose alone
    (r,) = join.due()
    assert (r.item, r.missing, r.dropped, r.counters) == ("pose3", ("ecm", "truth"), True, ("no_ecm",))
    free = FrameJoin([], max_wait=2)       # no waits: due at once
    free.hold(0, "x")
    assert [x.item for x in free.due()] == ["x"]


def test_a_frame_join_releases_as_the_seq_join_does():
    """The same release rule as SeqJoin, item for item, on a random stream."""
    import random

    from common.runtime.pairing import FrameJoin, Wait
    rng = random.Random(3)
    have = set()
    old = SeqJoin(max_wait=3, in_order=True)
    new = FrameJoin([Wait("x", lambda s, _: s in have)], max_wait=3, in_order=True)
    for _ in range(300):
        seq = rng.randrange(60)
        what = rng.random()
        if what < 0.4:
            old.hold(seq, seq)
            new.hold(seq, seq)
        elif what < 0.7:
            have.add(seq)
        else:
            old.see(seq)
            new.see(seq)
        assert old.due(lambda s, _: s in have) == [(r.item, r.complete) for r in new.due()]

"""Damaged and odd bags through ``needletrack dataset from-bag``: a clear error naming the file and
where (no traceback, exit 1, no folder left behind), an unfinished recording read up to its last
complete chunk, a topic of an unresolvable type ignored unless the conversion needs it. The bags
are small synthetic ones (common/ros/bagfuzz.py), damaged the way the probe of issue 32 did."""
import os
import random
import struct

import pytest
import yaml

from common.cli import dataset_main
from common.data.check import check_dataset
from common.data.dataset import Dataset
from common.data.writer import staged_folder
from common.ros.bag import BagError, BagStereo
from common.ros.bagfuzz import damage_mcap, fuzz_bags, mcap_records, synthetic_bag, topic_map


@pytest.fixture()
def tm(tmp_path):
    p = tmp_path / "topics.yaml"
    p.write_text(yaml.safe_dump(topic_map()))
    return str(p)


def from_bag(bag, out, tm, capsys):
    rc = dataset_main(["from-bag", str(bag), "--topics", tm, "--out", str(out), "--quiet"])
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


def assert_refused(bag, tmp_path, tm, capsys, *patterns):
    out = tmp_path / "out"
    rc, _, err = from_bag(bag, out, tm, capsys)
    assert rc == 1, err
    assert err.startswith("error: ") and "Traceback" not in err, err
    assert str(bag) in err, err
    for p in patterns:
        assert p in err, (p, err)
    assert not out.exists()                                     # nothing that could pass `dataset check`
    assert not [f for f in os.listdir(tmp_path) if ".partial-" in f]
    return err


@pytest.mark.slow
def test_a_clean_synthetic_bag_converts(tmp_path, tm, capsys):
    bag = synthetic_bag(str(tmp_path / "ok.mcap"), 6)
    rc, out, err = from_bag(bag, tmp_path / "ds", tm, capsys)
    assert rc == 0, err
    ds = Dataset(tmp_path / "ds")
    assert len(ds) == 6 and not check_dataset(ds).errors


@pytest.mark.slow
def test_a_corrupt_zstd_chunk_a_crc_mismatch_and_a_4gb_length_are_errors_naming_the_file(tmp_path, tm, capsys):
    data = open(synthetic_bag(str(tmp_path / "ok.mcap"), 6), "rb").read()
    chunks = [r for r in mcap_records(data) if r[0] == 0x06]
    assert len(chunks) == 6
    op, off, ln = chunks[3]                        # frame 3's chunk: frames 0..2 come out first
    b = bytearray(data)
    b[off + 9 + 60:off + 9 + 90] = b"\x00" * 30
    (tmp_path / "zstd.mcap").write_bytes(bytes(b))
    err = assert_refused(tmp_path / "zstd.mcap", tmp_path, tm, capsys, "unreadable after")
    assert "/cam/" in err or "/ecm/pose" in err                 # the last topic read: the position
    b = bytearray(data)
    struct.pack_into("<I", b, off + 9 + 24, 12345)
    (tmp_path / "crc.mcap").write_bytes(bytes(b))
    assert_refused(tmp_path / "crc.mcap", tmp_path, tm, capsys, "unreadable", "checksum")
    b = bytearray(data)
    struct.pack_into("<Q", b, mcap_records(data)[-3][1] + 1, 4 * 2**30 + 5)   # a summary record's length
    (tmp_path / "len.mcap").write_bytes(bytes(b))
    rc, _, err = from_bag(tmp_path / "len.mcap", tmp_path / "len_out", tm, capsys)
    assert "Traceback" not in err and (rc == 0 or err.startswith("error: "))


def test_a_truncated_ros1_bag_and_a_4gb_record_length_are_errors(tmp_path, tm, capsys):
    bag = synthetic_bag(str(tmp_path / "ok.bag"), 6, ros=1)
    data = open(bag, "rb").read()
    (tmp_path / "cut.bag").write_bytes(data[:len(data) * 2 // 3])
    assert_refused(tmp_path / "cut.bag", tmp_path, tm, capsys)
    b = bytearray(data)
    struct.pack_into("<I", b, 13, 0xFFFFFFF0)                   # the first record's header length
    (tmp_path / "len.bag").write_bytes(bytes(b))
    assert_refused(tmp_path / "len.bag", tmp_path, tm, capsys)


def test_a_last_right_image_of_another_size_leaves_no_folder(tmp_path, tm, capsys):
    bag = synthetic_bag(str(tmp_path / "size.mcap"), 6, last_right_size=(32, 24))
    assert_refused(bag, tmp_path, tm, capsys, "right image 32x24 differ in size")


def test_non_finite_values_are_named_not_written(tmp_path, tm, capsys):
    bag = synthetic_bag(str(tmp_path / "nanpose.mcap"), 6, nan_pose_at=3)
    assert_refused(bag, tmp_path, tm, capsys, "/ecm/pose: T_world_ecm is not finite", "frame 3")
    bag = synthetic_bag(str(tmp_path / "naninfo.mcap"), 6, nan_info_at=2)
    err = assert_refused(bag, tmp_path, tm, capsys, "/cam/left/camera_info: the left camera's K is not finite")
    assert "changed" not in err


def test_an_unfinished_recording_gives_its_complete_chunks_and_says_so(tmp_path, tm, capsys):
    bag = synthetic_bag(str(tmp_path / "killed.mcap"), 6, finish=False)
    rc, out, err = from_bag(bag, tmp_path / "ds", tm, capsys)
    assert rc == 0, err
    assert "recovered 30 messages from the 6 complete chunks of an unfinished recording" in err
    assert len(Dataset(tmp_path / "ds")) == 6
    # cut inside its last chunk: the frames before it
    data = open(bag, "rb").read()
    last = [r for r in mcap_records(data) if r[0] == 0x06][-1]
    (tmp_path / "cut.mcap").write_bytes(data[:last[1] + last[2] // 2])
    with BagStereo(tmp_path / "cut.mcap", topics=topic_map()) as src:
        assert len(list(src)) == 5
        assert "from the 5 complete chunks" in src.info["recovered"]
    # a finished file with its summary and footer cut off reads the same way
    finished = open(synthetic_bag(str(tmp_path / "done.mcap"), 6), "rb").read()
    data_end = next(o for op, o, _ in mcap_records(finished) if op == 0x0F)
    (tmp_path / "nosummary.mcap").write_bytes(finished[:data_end])
    with BagStereo(tmp_path / "nosummary.mcap", topics=topic_map()) as src:
        assert len(list(src)) == 6 and src.info["recovered"]
    (tmp_path / "header_only.mcap").write_bytes(data[:mcap_records(data)[1][1]])
    assert_refused(tmp_path / "header_only.mcap", tmp_path, tm, capsys, "nothing to recover")


def _unresolvable_topic(out):
    conn = out.w.add_connection("/weird", "foo_msgs/msg/Bar", msgdef="baz_msgs/Qux q\nint32 x\n",
                                md5sum="0123456789abcdef0123456789abcdef")
    out.w.write(conn, 10**18, b"\x00" * 8)


def test_an_unrelated_topic_of_an_unresolvable_type_is_ignored_a_needed_one_named(tmp_path, tm, capsys):
    bag = synthetic_bag(str(tmp_path / "weird.bag"), 4, ros=1, extra=_unresolvable_topic)
    rc, _, err = from_bag(bag, tmp_path / "ds", tm, capsys)
    assert rc == 0, err
    assert len(Dataset(tmp_path / "ds")) == 4
    m = {**topic_map(), "ecm_pose": "/weird"}
    with pytest.raises(BagError, match=r"topic /weird \(ecm_pose\): type foo_msgs/msg/Bar cannot be resolved"):
        BagStereo(bag, topics=m)


def test_staged_folder_renames_on_success_and_removes_on_failure(tmp_path):
    with staged_folder(str(tmp_path / "a")) as d:
        (open(os.path.join(d, "x"), "w")).close()
    assert (tmp_path / "a" / "x").exists()
    with pytest.raises(RuntimeError):
        with staged_folder(str(tmp_path / "b")) as d:
            raise RuntimeError("boom")
    assert sorted(os.listdir(tmp_path)) == ["a"]
    with pytest.raises(ValueError, match="exists and is not empty"):
        with staged_folder(str(tmp_path / "a")):
            pass
    (tmp_path / "empty").mkdir()
    with staged_folder(str(tmp_path / "empty")) as d:
        (open(os.path.join(d, "y"), "w")).close()
    assert (tmp_path / "empty" / "y").exists()


@pytest.mark.slow
def test_damaged_bags_never_crash_the_reader():
    """The fuzz target's bag files in small: every damage kind, MCAP and ROS 1."""
    r = fuzz_bags(14, seed=3, log=lambda *a: None)
    assert r.files == 28 and r.crashes == 0, r.first_crash
    assert r.refused > 0 and r.read > 0 and r.recovered > 0


def test_damage_kinds_change_the_file(tmp_path):
    from common.ros.bagfuzz import MCAP_KINDS
    base = open(synthetic_bag(str(tmp_path / "b.mcap"), 3), "rb").read()
    rng = random.Random(0)
    for kind in MCAP_KINDS:
        assert damage_mcap(base, kind, rng) != base, kind

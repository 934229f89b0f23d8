"""The message codec: exact round trips, the image fast path, and clear errors on bad payloads."""
import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from common.geometry.camera import StereoRig
from common.geometry.needle import NeedleModel
from common.runtime.messages import (
    MESSAGE_TYPES,
    Calibration,
    CameraImage,
    Command,
    EcmJoints,
    EcmPose,
    EndOfStream,
    GroundTruth,
    InHandPose,
    ArmCorrection,
    InstrumentState,
    Keypoints,
    LockRejected,
    MessageError,
    NodeStats,
    NoPoseNotice,
    Points3D,
    PoseEstimate,
    decode,
    encode,
)


def _calib():
    return Calibration(stamp_ns=5, image_size=np.array([1920, 1080]), cameras=StereoRig.default().to_dict(),
                       needle=NeedleModel().to_dict(), source="test")


def examples():
    T = np.eye(4)
    T[:3, 3] = [0.01, -0.02, 0.15]
    return [
        CameraImage.from_bgr("left", 7, 123, np.arange(4 * 6 * 3, dtype=np.uint8).reshape(4, 6, 3)),
        EcmJoints(seq=3, stamp_ns=10, q=np.array([0.1, -0.2, 0.05, 0.0])),
        EcmPose(seq=3, stamp_ns=10, T_world_ecm=T, q=np.zeros(4)),
        Keypoints("right", 9, 11, True, np.arange(10, dtype=float).reshape(5, 2), np.linspace(0, 1, 5), 0.9,
                  np.array([1.0, 2.0, 30.0, 40.0]), "oracle", None, np.zeros((7, 2)), np.ones(7)),
        Keypoints("left", 9, 11, True, np.ones((5, 2)), np.ones(5), 0.8, None, "learned", None, np.zeros((7, 2)),
                  np.ones(7), centreline_sigma_px=0.2, on_arc=np.array([False, True, True, True, False]),
                  centreline_corr_points=5.0, keypoint_sigma_px=1.0),
        Keypoints.not_found("left", 2, 3, "learned", "low confidence", 0.2),
        PoseEstimate(seq=4, stamp_ns=12, method="pnp_joint", T_ecm_needle=T, T_world_needle=T, residual=0.4,
                     residual_unit="px", n_views=2, covariance=np.eye(6) * 1e-6, ambiguous=False,
                     points_ecm=np.zeros((5, 3)), sequence=1, end_identity=0.8),
        NoPoseNotice(seq=4, stamp_ns=12, method="refined", reason="too_few_points"),
        NoPoseNotice(seq=5, stamp_ns=13, method="tracked", reason="no_track", epoch=77),
        LockRejected(seq=6, stamp_ns=14, camera="right", reason="wrong_lock", bbox=np.array([1.0, 2.0, 30.0, 40.0])),
        LockRejected(seq=7, stamp_ns=15, camera="left", reason="wrong_lock"),
        Points3D(seq=1, stamp_ns=2, points_ecm=np.full((5, 3), np.nan), valid=np.zeros(5, dtype=bool)),
        GroundTruth(seq=1, stamp_ns=2, sequence=0, step=1, ecm_joints=np.zeros(4), T_world_ecm=T,
                    T_world_needle=T, keypoints={"left": np.zeros((5, 2)), "right": np.ones((5, 2))},
                    visible={"left": np.ones(5, dtype=bool), "right": np.zeros(5, dtype=bool)}),
        GroundTruth(seq=2, stamp_ns=3, sequence=4, step=2, T_world_needle=T, needle_at_rest=False),
        InstrumentState("psm1", seq=5, stamp_ns=6, T_world_jaw=T, jaw_rad=0.4, holds_needle=True),
        InstrumentState("psm2", seq=5, stamp_ns=6, T_world_jaw=np.eye(4), jaw_rad=0.0),
        Command("place_needle", {"distance_m": 0.15, "seed": 3}),
        NodeStats("det", "detector", 42, 1, 2.5, {"in.left": 3, "state": "active"}, {"in.left": 29.9}, 1.0, 2.0),
        EndOfStream(frames=30, stamp_ns=9),
        InHandPose("psm1", 5, 6, "psm1_jaw", T, np.eye(6) * 1e-8, 0.9),
        ArmCorrection("psm1", 5, 6, T, T, np.eye(6) * 1e-6),
    ]


def _equal(a, b):
    if isinstance(a, np.ndarray):
        return isinstance(b, np.ndarray) and a.dtype == b.dtype and a.shape == b.shape and \
            np.array_equal(a, b, equal_nan=a.dtype.kind == "f")
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(_equal(a[k], b[k]) for k in a)
    if isinstance(a, (bytes, memoryview)):
        return bytes(a) == bytes(b)
    return a == b


@pytest.mark.parametrize("msg", examples(), ids=lambda m: type(m).__name__)
def test_every_message_round_trips_exactly(msg):
    back = decode(encode(msg), type(msg))
    assert type(back) is type(msg)
    for name, value in msg.to_body().items():
        assert _equal(value, getattr(back, name)), name


def test_calibration_round_trips():
    c = _calib()
    back = decode(encode(c), Calibration)
    assert StereoRig.from_dict(back.cameras, back.image_size) is not None and back.source == "test"


def test_all_message_types_are_registered():
    assert {c.__name__ for c in MESSAGE_TYPES.values()} >= {
        "CameraImage", "EcmJoints", "EcmPose", "Keypoints", "PoseEstimate", "Points3D", "GroundTruth",
        "Calibration", "Command", "NodeStats", "EndOfStream", "InstrumentState", "InHandPose", "NoPoseNotice",
        "ArmCorrection", "LockRejected"}
    # every registered type is in the round trips and the corruption tests below (Calibration: its own)
    assert {type(m) for m in examples()} | {Calibration} == set(MESSAGE_TYPES.values())


@pytest.mark.parametrize("body,text", [
    ({"seq": 1, "stamp_ns": 2, "method": "", "reason": "poor_fit"},
     "NoPoseNotice.method: must be 1 to 64 letters, digits"),
    ({"seq": 1, "stamp_ns": 2, "method": "refined", "reason": "poor fit\n"},
     "NoPoseNotice.reason: must be 1 to 64 letters, digits"),
    ({"seq": 1, "stamp_ns": 2, "method": "refined", "reason": "x" * 65}, "NoPoseNotice.reason: must be 1 to 64"),
    ({"seq": 1, "stamp_ns": 2, "method": "refined", "reason": 3}, "NoPoseNotice.reason: expected string, got int"),
    ({"seq": -1, "stamp_ns": 2, "method": "refined", "reason": "poor_fit"}, "NoPoseNotice.seq: must not be negative"),
    ({"seq": 1, "stamp_ns": 2, "method": "refined"}, "NoPoseNotice.reason: missing"),
])
def test_a_no_pose_notice_with_bad_fields_is_refused(body, text):
    with pytest.raises(MessageError, match=text):
        decode(msgpack.packb({"schema": NoPoseNotice.SCHEMA, "version": 1, "body": body}), NoPoseNotice)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(hnp.arrays(st.sampled_from([np.float64, np.float32]), (5, 2),
                  elements=st.floats(-1e7, 1e7, width=32) | st.just(float("nan"))),   # NaN: missing
       st.integers(0, 2 ** 63 - 1))
def test_arrays_round_trip_with_dtype_shape_and_values(uv, seq):
    k = Keypoints("left", seq, 0, True, uv, np.ones(5, dtype=np.float32), 1.0)
    back = decode(encode(k), Keypoints)
    assert back.seq == seq and _equal(uv, back.uv) and back.scores.dtype == np.float32


def test_a_1080p_image_travels_as_a_view_of_the_payload():
    img = np.random.default_rng(0).integers(0, 255, (1080, 1920, 3), dtype=np.uint8)
    msg = CameraImage.from_bgr("right", 5, 99, img)
    payload = encode(msg)
    back = decode(payload, CameraImage)
    assert isinstance(back.data, memoryview)                      # no copy of the pixels
    assert np.array_equal(back.to_bgr(), img) and back.seq == 5 and back.camera == "right"
    plain = msgpack.unpackb(payload, raw=False)                   # still plain msgpack
    assert plain["schema"] == CameraImage.SCHEMA and plain["body"]["data"] == img.tobytes()
    view = CameraImage.from_bgr("left", 1, 2, img, copy=False)
    assert np.array_equal(decode(encode(view)).to_bgr(), img)


def test_encoded_images_decode_and_corrupt_ones_raise():
    img = np.zeros((20, 30, 3), np.uint8)
    img[5:10, 5:20] = 200
    for enc in ("png", "jpeg"):
        msg = decode(encode(CameraImage.from_bgr("left", 1, 2, img, enc)), CameraImage)
        assert msg.encoding == enc and msg.to_bgr().shape == img.shape
    bad = CameraImage("left", 1, 2, 30, 20, "png", b"\x89PNG not really")
    with pytest.raises(MessageError, match="CameraImage.data: not a png"):     # refused at decode
        decode(encode(bad), CameraImage)
    with pytest.raises(MessageError, match="CameraImage.data: corrupt png"):
        bad.to_bgr()


def test_truncated_large_payload_is_an_error_naming_the_field():
    img = np.zeros((300, 400, 3), np.uint8)
    payload = encode(CameraImage.from_bgr("left", 1, 2, img))
    with pytest.raises(MessageError):
        decode(payload[:-1000], CameraImage)
    wrong = msgpack.packb({"schema": CameraImage.SCHEMA, "version": 1, "body": {
        "camera": "left", "seq": 1, "stamp_ns": 2, "width": 400, "height": 300, "encoding": "bgr8",
        "data": b"\x00" * 1000}})
    with pytest.raises(MessageError, match=r"CameraImage.data: bgr8 400x300 needs 360000 bytes, got 1000"):
        decode(wrong)


@pytest.mark.parametrize("body,text", [
    ({"seq": "1", "stamp_ns": 0, "q": [0, 0, 0, 0]}, "EcmJoints.seq: expected int, got str"),
    ({"seq": 1, "stamp_ns": 0}, "EcmJoints.q: missing"),
    ({"seq": 1, "stamp_ns": 0, "q": [0, 0, 0]}, r"EcmJoints.q: expected shape \(4,\), got \(3,\)"),
    ({"seq": 1, "stamp_ns": 0, "q": [0, 0, 0, float("nan")]}, "EcmJoints.q: not finite"),
    ({"seq": 1, "stamp_ns": 0, "q": [0, 0, 0, 0], "extra": 1}, "EcmJoints.extra: unknown field"),
])
def test_decode_errors_name_the_message_and_the_field(body, text):
    payload = msgpack.packb({"schema": EcmJoints.SCHEMA, "version": 1, "body": body})
    with pytest.raises(MessageError, match=text):
        decode(payload, EcmJoints)


def test_envelope_errors():
    with pytest.raises(MessageError, match="Keypoints: got a EcmJoints instead"):
        decode(encode(EcmJoints(1, 2, np.zeros(4))), Keypoints)
    with pytest.raises(MessageError, match="unknown schema 'x.Y'"):
        decode(msgpack.packb({"schema": "x.Y", "version": 1, "body": {}}))
    with pytest.raises(MessageError, match="EcmJoints.version: expected 1, got 7"):
        decode(msgpack.packb({"schema": EcmJoints.SCHEMA, "version": 7, "body": {}}))
    with pytest.raises(MessageError, match="missing schema envelope"):
        decode(msgpack.packb([1, 2]))
    with pytest.raises(MessageError, match="not valid msgpack"):
        decode(b"\xc1\xc1")


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300))
def test_random_bytes_never_crash_the_decoder(data):
    try:
        decode(data)
    except MessageError:
        pass


@settings(max_examples=300, deadline=None)
@given(st.data())
def test_corrupted_messages_decode_or_raise_message_error(data):
    msg = data.draw(st.sampled_from(examples()))
    payload = bytearray(encode(msg))
    for _ in range(data.draw(st.integers(1, 4))):
        i = data.draw(st.integers(0, len(payload) - 1))
        payload[i] = data.draw(st.integers(0, 255))
    try:
        decode(bytes(payload))
    except MessageError:
        pass


def test_a_body_key_that_is_not_a_string_is_an_unknown_field():
    # found by hypothesis: a corrupted map key decodes as an int beside the string keys
    body = Keypoints("left", 1, 2, True, np.ones((5, 2)), np.ones(5), 0.9).to_body()
    payload = msgpack.packb({"schema": Keypoints.SCHEMA, "version": 1,
                             "body": {**body, "uv": body["uv"].tolist(), "scores": body["scores"].tolist(),
                                      7: 1, "zz": 2}}, strict_types=False)
    with pytest.raises(MessageError, match="Keypoints.7: unknown field"):
        decode(payload, Keypoints)


def test_keypoints_with_bad_noise_statements_are_refused():
    body = Keypoints("left", 1, 2, True, np.ones((5, 2)), np.ones(5), 0.9).to_body()
    cases = {"centreline_sigma_px": ((0.0, -0.2, float("nan")), "must be positive"),
             "centreline_corr_points": ((0.5, float("nan")), "must be at least 1"),
             "keypoint_sigma_px": ((0.0, -1.0, float("inf")), "must be positive")}
    for field, (bads, why) in cases.items():
        for bad in bads:
            payload = msgpack.packb({"schema": Keypoints.SCHEMA, "version": 1,
                                     "body": {**body, "uv": body["uv"].tolist(),
                                              "scores": body["scores"].tolist(), field: bad}})
            why_ = "not finite" if not np.isfinite(bad) else why      # non-finite: refused by the codec
            with pytest.raises(MessageError, match=f"Keypoints.{field}: {why_}"):
                decode(payload, Keypoints)


def test_ground_truth_from_a_dataset_frame_and_a_simulated_one():
    import numpy as np
    from common.data.dataset import Frame
    from common.runtime.messages import GroundTruth, decode, encode
    from common.sim.live import SimFrame
    assert GroundTruth.from_frame(Frame(0, 0, "l.png", "r.png"), 3, 7) is None
    kp = {c: np.arange(10.0).reshape(5, 2) + i for i, c in enumerate(("left", "right"))}
    vis = {"left": np.ones(5, bool), "right": np.array([1, 1, 0, 1, 1], bool)}
    bbox = {"left": [0.0, 1.0, 20.0, 30.0], "right": None}
    T = np.eye(4)
    T[:3, 3] = [0.01, 0.02, 0.1]
    fr = Frame(4, 5, "l.png", "r.png", sequence=2, step=1, ecm_joints=[0.1, 0.0, 0.05, 0.0],
               T_world_ecm=np.eye(4), T_world_needle=T, keypoints=kp, visible=vis, bbox=bbox)
    sim = SimFrame({}, np.array([0.1, 0.0, 0.05, 0.0]), np.eye(4), T,
                   {"keypoints": kp, "visible": vis, "bbox": bbox}, 2, 1)
    for frame in (fr, sim):
        gt = GroundTruth.from_frame(frame, 9, 11)
        back = decode(encode(gt))
        assert (back.seq, back.stamp_ns, back.sequence, back.step) == (9, 11, 2, 1)
        assert np.allclose(back.ecm_joints, [0.1, 0.0, 0.05, 0.0]) and np.allclose(back.T_world_needle, T)
        assert np.allclose(back.keypoints["right"], kp["right"]) and back.visible["right"].tolist() == vis["right"].tolist()
        assert back.bbox["right"] is None and np.allclose(back.bbox["left"], bbox["left"])


@pytest.mark.parametrize("field,bad,text", [
    ("T_world_jaw", np.diag([1.0, 1.0, 1.0, 2.0]).tolist(), "InstrumentState.T_world_jaw"),
    ("T_world_jaw", np.eye(3).tolist(), r"InstrumentState.T_world_jaw: expected shape \(4, 4\)"),
    ("jaw_rad", -0.1, r"InstrumentState.jaw_rad: an opening angle in \[0, pi\]"),
    ("jaw_rad", float("nan"), "InstrumentState.jaw_rad: not finite"),
    ("name", "", "InstrumentState.name: 1 to 32 printable characters"),
    ("holds_needle", 1, "InstrumentState.holds_needle: expected bool"),
])
def test_instrument_states_with_bad_fields_are_refused(field, bad, text):
    body = InstrumentState("psm1", 1, 2, np.eye(4), 0.3).to_body()
    body = {**body, "T_world_jaw": body["T_world_jaw"].tolist(), field: bad}
    with pytest.raises(MessageError, match=text):
        decode(msgpack.packb({"schema": InstrumentState.SCHEMA, "version": 1, "body": body}), InstrumentState)


def test_instrument_state_from_a_dataset_frame_and_moving_truth_is_no_multiview_group():
    from common.data.instruments import InstrumentPose
    T = np.eye(4)
    T[:3, 3] = [0.01, 0.0, 0.03]
    msg = decode(encode(InstrumentState.from_pose("psm2", InstrumentPose(T, 0.25, False), 7, 8)))
    assert (msg.name, msg.seq, msg.stamp_ns, msg.jaw_rad, msg.holds_needle) == ("psm2", 7, 8, 0.25, False)
    assert np.array_equal(msg.T_world_jaw, T)
    assert GroundTruth(1, 2, sequence=3).multiview_group == 3
    assert GroundTruth(1, 2, sequence=3, needle_at_rest=True).multiview_group == 3
    assert GroundTruth(1, 2, sequence=3, needle_at_rest=False).multiview_group is None

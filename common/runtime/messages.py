"""Messages the dataflow carries, and their msgpack codec (no pickle).

Every payload is a msgpack map ``{"schema": NAME, "version": V, "body": {...}}``. numpy arrays
travel as a msgpack extension (dtype, shape, raw bytes) and round-trip exactly. ``decode``
validates the schema, version and every field, and raises ``MessageError`` naming the message
type and the field.

Stereo frames travel as two ``CameraImage`` messages (one per camera) that share ``seq``;
consumers pair them by ``seq`` (see ``common.runtime.pairing``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal, Optional

import msgspec
import numpy as np

from common.frames import CAMERAS  # noqa: F401  (re-exported)
from common.methods import TRACK_MODES
from common.runtime.checks import (  # noqa: F401  (re-exported: the messages' API)
    MAX_ARRAY_ELEMENTS,
    MAX_COORD,
    MAX_IMAGE_SIDE,
    MAX_INT,
    RIGID_TOL,
    MessageError,
    finite_array,
    require_rigid,
    covariance_error,
    image_header_size,
    pose_invariant_error,
    rigid_error,
)
from common.constraints import NonNegativeNumber, Probability
from common.runtime.codec import Message, decode, encode, encode_parts, register, registered_types  # noqa: F401
from common.runtime.schema import Array, ArrayNaN, ByCamera, Bytes, Int64, NonNegative, Number, Says, number

# ---------------------------------------------------------------- the messages

ENCODINGS = ("bgr8", "png", "jpeg")

PositivePx = number("must be positive, got {value}", gt=0)
"""A 1-sigma error in pixels: finite and positive."""
AtLeastOne = number("must be at least 1, got {value}", ge=1)
Share = number("must be a share in [0, 1], got {value}", ge=0, le=1)
Word = Annotated[str, msgspec.Meta(pattern=r"^[A-Za-z0-9_.-]{1,64}$"),
                 Says("must be 1 to 64 letters, digits, '_', '.' or '-', got {value!r}")]
"""A name a node makes up and a counter carries: a method, a reason."""


@register
@dataclass
class CameraImage(Message):
    """One camera's image of a stereo frame. ``data`` is raw BGR (h*w*3 bytes) or a PNG/JPEG file.

    A decoded image's ``data`` may be a read-only memoryview of the payload (no copy); use
    ``to_bgr()`` or ``bytes(msg.data)``.
    """

    SCHEMA = "needletrack.CameraImage"
    camera: Literal[CAMERAS]
    seq: NonNegative
    stamp_ns: NonNegative
    width: Int64
    height: Int64
    encoding: Literal[ENCODINGS]
    data: Bytes
    epoch: Optional[NonNegative] = None

    def validate(self):
        if not (1 <= self.width <= MAX_IMAGE_SIDE and 1 <= self.height <= MAX_IMAGE_SIDE):
            raise MessageError(f"CameraImage.width/height: must be in 1..{MAX_IMAGE_SIDE}, got {self.width}x{self.height}")
        if self.encoding == "bgr8" and len(self.data) != self.width * self.height * 3:
            raise MessageError(f"CameraImage.data: bgr8 {self.width}x{self.height} needs "
                               f"{self.width * self.height * 3} bytes, got {len(self.data)}")
        if self.encoding != "bgr8":
            size = image_header_size(self.data)
            if size is None:
                raise MessageError(f"CameraImage.data: not a {self.encoding} file ({len(self.data)} bytes)")
            if size != (self.width, self.height):
                raise MessageError(f"CameraImage.data: the {self.encoding} header says {size[0]}x{size[1]}, "
                                   f"the message {self.width}x{self.height}")

    @classmethod
    def from_bgr(cls, camera: str, seq: int, stamp_ns: int, img: np.ndarray, encoding: str = "bgr8",
                 jpeg_quality: int = 95, copy: bool = True) -> "CameraImage":
        """``copy=False`` (bgr8) keeps a view of ``img`` instead of copying it: only for an
        array the caller will not modify while the message is in use."""
        h, w = img.shape[:2]
        if encoding == "bgr8":
            arr = np.ascontiguousarray(img, dtype=np.uint8)
            data = arr.tobytes() if copy else memoryview(arr.reshape(-1))
        else:
            import cv2
            ext = ".png" if encoding == "png" else ".jpg"
            params = [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality] if encoding == "jpeg" else []
            ok, buf = cv2.imencode(ext, img, params)
            if not ok:
                raise MessageError(f"CameraImage.data: could not encode {encoding}")
            data = buf.tobytes()
        return cls(camera, seq, stamp_ns, w, h, encoding, data)

    def to_bgr(self) -> np.ndarray:
        """The pixels as an (h, w, 3) uint8 BGR array; raises MessageError on corrupt data."""
        if self.encoding == "bgr8":
            return np.frombuffer(self.data, np.uint8).reshape(self.height, self.width, 3)
        import cv2
        size = image_header_size(self.data)                       # checked before decoding
        if size is None:
            raise MessageError(f"CameraImage.data: corrupt {self.encoding} ({len(self.data)} bytes, no header)")
        if size != (self.width, self.height):
            raise MessageError(f"CameraImage.data: the {self.encoding} header says {size[0]}x{size[1]}, "
                               f"the message {self.width}x{self.height}")
        try:
            img = cv2.imdecode(np.frombuffer(self.data, np.uint8), cv2.IMREAD_COLOR)
        except cv2.error as exc:
            raise MessageError(f"CameraImage.data: corrupt {self.encoding}: {str(exc).strip()[:200]}") from None
        if img is None:
            raise MessageError(f"CameraImage.data: corrupt {self.encoding} ({len(self.data)} bytes)")
        if img.shape[:2] != (self.height, self.width):
            raise MessageError(f"CameraImage.data: decoded {img.shape[1]}x{img.shape[0]}, "
                               f"header says {self.width}x{self.height}")
        return img


@register
@dataclass
class EcmJoints(Message):
    """ECM joint state q = [yaw, pitch, insertion, roll] (rad, rad, m, rad)."""

    SCHEMA = "needletrack.EcmJoints"
    seq: NonNegative
    stamp_ns: NonNegative
    q: Array[4]
    epoch: Optional[NonNegative] = None

    def validate(self):
        if not np.all(np.isfinite(self.q)):
            raise MessageError("EcmJoints.q: not finite")


@register
@dataclass
class EcmPose(Message):
    """Endoscope pose from forward kinematics: ``T_world_ecm`` at a joint state, and the
    cameras' poses ``T_world_left``/``T_world_right`` when the calibration is known."""

    SCHEMA = "needletrack.EcmPose"
    seq: NonNegative
    stamp_ns: NonNegative
    T_world_ecm: Array[4, 4]
    q: Optional[Array[4]] = None
    T_world_left: Optional[Array[4, 4]] = None
    T_world_right: Optional[Array[4, 4]] = None
    epoch: Optional[NonNegative] = None

    def validate(self):
        for name in ("T_world_ecm", "T_world_left", "T_world_right"):
            require_rigid(getattr(self, name), f"EcmPose.{name}")


@register
@dataclass
class Keypoints(Message):
    """A detector's output for one camera image.

    ``found`` is False for "no needle" (then ``reason`` says why and ``uv`` is all NaN).
    ``uv`` (5, 2) pixels of A..E, ``scores`` (5,) in [0, 1], ``confidence`` overall in [0, 1],
    ``bbox`` [x0, y0, x1, y1] pixels. ``centreline`` optionally carries the dense observation
    of the needle's projected arc, (N, 2) pixels ordered from A to E, with ``centreline_w`` (N,),
    and optionally ``centreline_sigma_px``, the detector's 1-sigma error of a centreline point
    across the curve (px; absent: the consumer's default), and ``centreline_corr_points``, how
    many consecutive points' errors move together (>= 1; absent: independent). ``on_arc`` (5,) optionally marks (1)
    the keypoints the detector placed on its fitted arc instead of observing them on their own.
    ``keypoint_sigma_px`` optionally states the 1-sigma error of a keypoint per image axis as a
    stereo fit should take it (px; errors the two cameras' detections share included; absent:
    the consumer's default). ``end_identity`` optionally states the probability that A is the
    needle's tip as said (0.5: the image cannot tell the tip from the tail; absent: A is taken as
    said). ``unfamiliarity`` optionally states how unlike the detector's training looks the
    image is (about 1: familiar; larger: less so; ``common.detector.familiarity``). ``visibility``
    (5,) optionally states the probability that each keypoint is seen (not inside tissue, not behind
    an instrument); a detector that states it caps each score at it.
    """

    SCHEMA = "needletrack.Keypoints"
    camera: Literal[CAMERAS]
    seq: NonNegative
    stamp_ns: NonNegative
    found: bool
    uv: ArrayNaN[5, 2]
    scores: Array[5]
    confidence: Number
    bbox: Optional[Array[4]] = None
    detector: str = ""
    reason: Optional[str] = None
    centreline: Optional[Array[None, 2]] = None
    centreline_w: Optional[Array[None]] = None
    centreline_sigma_px: Optional[PositivePx] = None
    on_arc: Optional[Array[5]] = None
    centreline_corr_points: Optional[AtLeastOne] = None
    keypoint_sigma_px: Optional[PositivePx] = None
    end_identity: Optional[Probability] = None
    epoch: Optional[NonNegative] = None
    unfamiliarity: Optional[NonNegativeNumber] = None
    visibility: Optional[Array[5]] = None

    def validate(self):
        pass

    @classmethod
    def not_found(cls, camera: str, seq: int, stamp_ns: int, detector: str, reason: str,
                  confidence: float = 0.0) -> "Keypoints":
        return cls(camera, seq, stamp_ns, False, np.full((5, 2), np.nan), np.zeros(5),
                   float(confidence), None, detector, reason)


@register
@dataclass
class PoseEstimate(Message):
    """A needle pose. ``T_ecm_needle`` maps needle to ECM frame (m). ``residual`` is the
    method's RMS (reprojection px, or registration m, as ``residual_unit`` says).
    ``covariance`` (6, 6) over [rotation vector (rad), translation (m)] in the ECM frame, when known.
    ``model_sigma_m``, ``model_sigma_rad``: the part of the position and orientation error,
    1 sigma per axis (m, rad), that every estimate of this needle shares (the needle model's and
    the rig's own error; already inside ``covariance``): a fusion of views does not average it down.
    ``end_identity``: the probability that the needle's tip is where this pose puts it; the other
    answer is the pose turned end for end (``common.geometry.refine.tip_for_tail``, the same arc).
    Absent: the detectors stated nothing (A was taken as the tip).
    ``identity_widened``: whether ``covariance`` was widened to span the turn end for end (its tip
    unsure, below ``common.geometry.end_identity.TIP_SURE``: ``C + (1 - end_identity) d d^T``), so
    that a consumer weighing both readings itself takes exactly that out
    (``end_identity.reading_covariance``); absent: not stated (a foreign source).
    ``mode``: a tracker's decision at this frame, from what it measures (``TRACK_MODES``):
    ``rest`` the needle at rest in the world, ``held`` in an instrument's jaws, ``free`` moving on
    its own; absent: no tracker decided (docs/tracking.md). The fusion fuses only views at rest.
    ``arc_seen``: the share of the needle's arc the pose was fitted to, in its better-seen camera
    (``common.geometry.arc_support``); absent: not measured.
    """

    SCHEMA = "needletrack.PoseEstimate"
    seq: NonNegative
    stamp_ns: NonNegative
    method: str
    T_ecm_needle: Array[4, 4]
    T_world_needle: Optional[Array[4, 4]] = None
    T_world_ecm: Optional[Array[4, 4]] = None
    residual: Number = 0.0
    residual_unit: Optional[str] = None
    n_views: Int64 = 1
    covariance: Optional[Array[6, 6]] = None
    ambiguous: Optional[bool] = None
    points_ecm: Optional[ArrayNaN[None, 3]] = None
    sequence: Optional[Int64] = None
    epoch: Optional[NonNegative] = None
    model_sigma_m: Optional[Number] = None
    model_sigma_rad: Optional[Number] = None
    end_identity: Optional[Number] = None
    mode: Optional[Literal[TRACK_MODES]] = None
    arc_seen: Optional[Share] = None
    identity_widened: Optional[bool] = None

    def validate(self):
        err = pose_invariant_error(self)
        if err:
            raise MessageError(err)


@register
@dataclass
class NoPoseNotice(Message):
    """A pose node's word that frame ``seq`` has no pose of ``method`` (``PoseEstimate.method``):
    ``reason`` why, as the node counts it (``no_pose.<reason>``, e.g. ``too_few_points``,
    ``poor_fit``; the tracker's ``no_track``). ``stamp_ns``: the frame's. What waits on the
    node's poses (the tracker on the refined ones, the fusion on the tracker's mode) goes on at
    once instead of waiting ``max_wait`` frames for a pose that will not come (docs/tracking.md)."""

    SCHEMA = "needletrack.NoPoseNotice"
    seq: NonNegative
    stamp_ns: NonNegative
    method: Word
    reason: Word
    epoch: Optional[NonNegative] = None

    def validate(self):
        pass


@register
@dataclass
class LockRejected(Message):
    """A pose node's word to a detector that camera ``camera``'s detection in frame ``seq`` is a
    wrong lock: the other camera's detection and the track disagree with it
    (``common.geometry.stereo_agreement``). The detector drops that camera's tracked crop and
    searches it cold, trying elsewhere than ``bbox`` ([x0, y0, x1, y1] px, the rejected
    detection's box; absent: anywhere) first. ``reason``: why, as the node counts it."""

    SCHEMA = "needletrack.LockRejected"
    seq: NonNegative
    stamp_ns: NonNegative
    camera: Literal[CAMERAS]
    reason: Word
    bbox: Optional[Array[4]] = None
    epoch: Optional[NonNegative] = None

    def validate(self):
        pass


@register
@dataclass
class Points3D(Message):
    """Triangulated keypoints A..E in the ECM frame (m); NaN rows where a point is missing."""

    SCHEMA = "needletrack.Points3D"
    seq: NonNegative
    stamp_ns: NonNegative
    points_ecm: ArrayNaN[5, 3]
    valid: Array[5]
    epoch: Optional[NonNegative] = None

    def validate(self):
        pass


@register
@dataclass
class GroundTruth(Message):
    """Per-frame ground truth, with the dataset spec's optional per-frame fields.
    ``needle_at_rest`` False: the needle moves within its ``sequence`` (a take, not a multi-view
    group; see ``multiview_group``)."""

    SCHEMA = "needletrack.GroundTruth"
    seq: NonNegative
    stamp_ns: NonNegative
    sequence: Optional[Int64] = None
    step: Optional[Int64] = None
    ecm_joints: Optional[Array[4]] = None
    T_world_ecm: Optional[Array[4, 4]] = None
    T_world_needle: Optional[Array[4, 4]] = None
    keypoints: Optional[ByCamera[Array[5, 2]]] = None
    visible: Optional[ByCamera[Array[5]]] = None
    bbox: Optional[ByCamera[Array[4]]] = None
    epoch: Optional[NonNegative] = None
    needle_at_rest: Optional[bool] = None

    def validate(self):
        for name in ("T_world_ecm", "T_world_needle"):
            require_rigid(getattr(self, name), f"GroundTruth.{name}")

    @property
    def multiview_group(self) -> Optional[int]:
        """The ``sequence`` when its frames show one needle at rest (a multi-view group), else
        None: each frame of a moving take is a view of its own."""
        return None if self.needle_at_rest is False else self.sequence

    @classmethod
    def from_frame(cls, frame, seq: int, stamp_ns: int) -> "GroundTruth | None":
        """The ground truth of a frame: a dataset's (``common.data.dataset.Frame``) or the
        simulator's (``common.sim.live.SimFrame``), anything with ``sequence``, ``step``,
        ``ecm_joints``, ``T_world_ecm``, ``T_world_needle`` and ``keypoints`` / ``visible`` /
        ``bbox`` by camera (each may be None), and optionally ``needle_at_rest``. None when the
        frame has no truth at all."""
        kp, vis, bbox = frame.keypoints, frame.visible, frame.bbox
        if all(v is None for v in (frame.T_world_needle, kp, vis, bbox, frame.T_world_ecm)):
            return None
        q = frame.ecm_joints
        return cls(seq=seq, stamp_ns=stamp_ns, sequence=frame.sequence, step=frame.step,
                   ecm_joints=None if q is None else np.asarray(q, float),
                   T_world_ecm=frame.T_world_ecm, T_world_needle=frame.T_world_needle,
                   keypoints=None if kp is None else {c: np.asarray(kp[c], float) for c in CAMERAS},
                   visible=None if vis is None else {c: np.asarray(vis[c], bool) for c in CAMERAS},
                   bbox=None if bbox is None else {c: None if bbox[c] is None else np.asarray(bbox[c], float)
                                                   for c in CAMERAS},
                   needle_at_rest=getattr(frame, "needle_at_rest", None))


@register
@dataclass
class InstrumentState(Message):
    """A patient-side instrument's measured state, as a dVRK PSM reports it: ``name`` (``psm1``,
    ``psm2``), ``T_world_jaw`` the jaw frame in world (m; origin at the jaws' pivot, z along the
    closed jaws towards their tips, y the axis they open about: ``docs/dataset.md``), ``jaw_rad``
    the opening (rad, 0 closed), both as the arm reports them (with its kinematic error).
    ``seq`` is the camera frame it belongs to; ``stamp_ns`` the measurement's time. Ground truth,
    from a simulator or a labelled dataset: ``holds_needle``, and ``T_world_jaw_truth`` /
    ``jaw_rad_truth`` where the report differs from the truth (absent: the report is exact)."""

    SCHEMA = "needletrack.InstrumentState"
    name: str
    seq: NonNegative
    stamp_ns: NonNegative
    T_world_jaw: Array[4, 4]
    jaw_rad: Number
    holds_needle: Optional[bool] = None
    epoch: Optional[NonNegative] = None
    T_world_jaw_truth: Optional[Array[4, 4]] = None
    jaw_rad_truth: Optional[Number] = None

    def validate(self):
        if not 1 <= len(self.name) <= 32 or not self.name.isprintable():
            raise MessageError(f"InstrumentState.name: 1 to 32 printable characters, got {self.name[:40]!r}")
        require_rigid(self.T_world_jaw, "InstrumentState.T_world_jaw")
        if self.T_world_jaw_truth is not None:
            require_rigid(self.T_world_jaw_truth, "InstrumentState.T_world_jaw_truth")
        for field, jaw in (("jaw_rad", self.jaw_rad), ("jaw_rad_truth", self.jaw_rad_truth)):
            if jaw is not None and not 0.0 <= jaw <= np.pi:
                raise MessageError(f"InstrumentState.{field}: an opening angle in [0, pi] rad, got {jaw:g}")

    @property
    def T_world_jaw_true(self) -> np.ndarray:
        """The true jaw pose: ``T_world_jaw_truth`` where given, else the reported one (then exact)."""
        return self.T_world_jaw if self.T_world_jaw_truth is None else self.T_world_jaw_truth

    @classmethod
    def from_pose(cls, name: str, pose, seq: int, stamp_ns: int) -> "InstrumentState":
        """From a dataset frame's instrument (anything with ``T_world_jaw``, ``jaw_rad``,
        ``holds_needle``, ``T_world_jaw_truth``, ``jaw_rad_truth``:
        ``common.data.instruments.InstrumentPose``)."""
        T_truth, jaw_truth = pose.T_world_jaw_truth, pose.jaw_rad_truth
        return cls(name, seq, stamp_ns, np.asarray(pose.T_world_jaw, float), float(pose.jaw_rad),
                   pose.holds_needle, T_world_jaw_truth=None if T_truth is None else np.asarray(T_truth, float),
                   jaw_rad_truth=None if jaw_truth is None else float(jaw_truth))


@register
@dataclass
class Command(Message):
    """A request to a node (e.g. the sim's ``place_needle``); ``args`` is a plain map."""

    SCHEMA = "needletrack.Command"
    name: str
    args: Optional[dict] = None

    def validate(self):
        pass


@register
@dataclass
class NodeStats(Message):
    """A node's periodic statistics, published on its stats key. ``proc_ms_p50``/``p99``: handler
    times of the messages whose handler published (the frame's work; a sink: every message)."""

    SCHEMA = "needletrack.NodeStats"
    node: str
    module: str
    pid: Int64
    stamp_ns: NonNegative
    uptime_s: Number
    counters: dict
    rates_hz: dict
    proc_ms_p50: Number
    proc_ms_p99: Number

    def validate(self):
        pass


@register
@dataclass
class EndOfStream(Message):
    """Sent by a finite source (replay) after its last frame: ``frames`` were published."""

    SCHEMA = "needletrack.EndOfStream"
    frames: NonNegative
    stamp_ns: NonNegative

    def validate(self):
        pass


@register
@dataclass
class Calibration(Message):
    """What a camera source knows of its rig, published before its first frame and then once a
    second: ``cameras`` and ``image_size`` as in dataset.yaml, ``needle`` (radius_m,
    keypoint_angles_deg) and optionally ``ecm`` (T_world_base, L_rcc, L_scopelen)."""

    SCHEMA = "needletrack.Calibration"
    stamp_ns: NonNegative
    image_size: Array[2]
    cameras: dict
    needle: dict
    ecm: Optional[dict] = None
    source: Optional[str] = None

    def validate(self):
        w, h = (float(x) for x in np.asarray(self.image_size, dtype=float))
        if not (1 <= w <= MAX_IMAGE_SIDE and 1 <= h <= MAX_IMAGE_SIDE and w == int(w) and h == int(h)):
            raise MessageError(f"Calibration.image_size: expected two whole numbers in 1..{MAX_IMAGE_SIDE}, "
                               f"got {self.image_size.tolist()}")
        for name in CAMERAS:
            cam = self.cameras.get(name)
            if not isinstance(cam, dict):
                raise MessageError(f"Calibration.cameras.{name}: expected a map with K, T_ecm_cam")
            for key, shape in (("K", (3, 3)), ("T_ecm_cam", (4, 4)), ("dist", None)):
                if key == "dist" and cam.get(key) is None:
                    continue
                a = finite_array(f"Calibration.cameras.{name}.{key}", cam.get(key), shape)
                if key == "dist" and len(a) not in (4, 5, 8, 12, 14):
                    raise MessageError(f"Calibration.cameras.{name}.dist: OpenCV takes 4, 5, 8, 12 or 14 "
                                       f"coefficients, got {len(a)}")
        finite_array("Calibration.needle.radius_m", self.needle.get("radius_m", 0.01), ())
        if "keypoint_angles_deg" in self.needle:
            finite_array("Calibration.needle.keypoint_angles_deg", self.needle["keypoint_angles_deg"], (5,))
        if self.ecm is not None:
            finite_array("Calibration.ecm.T_world_base", self.ecm.get("T_world_base", np.eye(4)), (4, 4))
            for key in ("L_rcc", "L_scopelen"):
                finite_array(f"Calibration.ecm.{key}", self.ecm.get(key, 0.0), ())
        # ranges, and what every consumer builds from it (rig, needle, arm), built once here
        for name in CAMERAS:
            K = np.asarray(self.cameras[name]["K"], dtype=float)
            if not (K[0, 0] > 0 and K[1, 1] > 0 and K[1, 0] == 0 and (K[2] == (0.0, 0.0, 1.0)).all()):
                raise MessageError(f"Calibration.cameras.{name}.K: must be a pinhole matrix [[fx, s, cx], "
                                   f"[0, fy, cy], [0, 0, 1]] with positive focal lengths, got {K.tolist()}"[:300])
            require_rigid(self.cameras[name]["T_ecm_cam"], f"Calibration.cameras.{name}.T_ecm_cam")
        r = float(np.asarray(self.needle.get("radius_m", 0.01), dtype=float))
        if not 0 < r < 1:
            raise MessageError(f"Calibration.needle.radius_m: must be in (0, 1) m, got {r:g}")
        if self.ecm is not None:
            require_rigid(self.ecm.get("T_world_base", np.eye(4)), "Calibration.ecm.T_world_base")
            for key in ("L_rcc", "L_scopelen"):
                v = float(np.asarray(self.ecm.get(key, 0.0), dtype=float))
                if not abs(v) <= 10:
                    raise MessageError(f"Calibration.ecm.{key}: must be within 10 m, got {v:g}")
        # the rest of what consumers build from it (the runtime builds no geometry itself)
        if "wire_diameter_m" in self.needle:
            w = finite_array("Calibration.needle.wire_diameter_m", self.needle["wire_diameter_m"], ())
            if not 0 < float(w) < 0.01:
                raise MessageError(f"Calibration.needle.wire_diameter_m: must be in (0, 0.01) m, got {float(w):g}")


@register
@dataclass
class InHandPose(Message):
    """The needle in the jaws that hold it, what a suturing planner drives along the arc:
    ``T_jaw_needle`` (4x4, m) in the jaw frame of instrument ``name`` (``docs/dataset.md``: origin at
    the jaws' pivot, z along the closed jaws), ``frame_id`` that frame's name (``<name>_jaw``,
    e.g. ``psm1_jaw``), ``covariance`` (6, 6) over [rotation vector (rad), translation (m)] in jaw
    axes (``R = exp([w]x) R0``, ``t = t0 + v``), ``end_identity`` the probability that the tip is
    where the pose puts it. ``seq``, ``stamp_ns``: the camera frame's (docs/tracking.md)."""

    SCHEMA = "needletrack.InHandPose"
    name: str
    seq: NonNegative
    stamp_ns: NonNegative
    frame_id: str
    T_jaw_needle: Array[4, 4]
    covariance: Array[6, 6]
    end_identity: Optional[Number] = None
    epoch: Optional[NonNegative] = None

    def validate(self):
        for label, text in (("name", self.name), ("frame_id", self.frame_id)):
            if not 1 <= len(text) <= 64 or not text.isprintable():
                raise MessageError(f"InHandPose.{label}: 1 to 64 printable characters, got {text[:40]!r}")
        require_rigid(self.T_jaw_needle, "InHandPose.T_jaw_needle")
        err = covariance_error(self.covariance, "InHandPose.covariance")
        if err:
            raise MessageError(err)
        if self.end_identity is not None and not 0.0 <= float(self.end_identity) <= 1.0:
            raise MessageError(f"InHandPose.end_identity: a probability in [0, 1], got {self.end_identity}")


@register
@dataclass
class ArmCorrection(Message):
    """An arm's kinematic error as the tracker estimates it (docs/tracking.md): ``T_correction``
    (4x4, world) corrects the arm's reported jaw pose, ``T_world_jaw_corrected = T_correction @
    T_world_jaw``; ``T_world_jaw`` that corrected pose in this frame (the arm's newest report);
    ``covariance`` (6, 6) of the corrected jaw pose over [rotation vector (rad), translation (m)]
    in world axes about the jaws' pivot (``R = exp([w]x) R0``, ``t = t0 + v``). ``name`` the
    instrument (``psm1``); ``seq``, ``stamp_ns``: the camera frame's."""

    SCHEMA = "needletrack.ArmCorrection"
    name: str
    seq: NonNegative
    stamp_ns: NonNegative
    T_correction: Array[4, 4]
    T_world_jaw: Array[4, 4]
    covariance: Array[6, 6]
    epoch: Optional[NonNegative] = None

    def validate(self):
        if not 1 <= len(self.name) <= 64 or not self.name.isprintable():
            raise MessageError(f"ArmCorrection.name: 1 to 64 printable characters, got {self.name[:40]!r}")
        require_rigid(self.T_correction, "ArmCorrection.T_correction")
        require_rigid(self.T_world_jaw, "ArmCorrection.T_world_jaw")
        err = covariance_error(self.covariance, "ArmCorrection.covariance")
        if err:
            raise MessageError(err)


MESSAGE_TYPES = registered_types()

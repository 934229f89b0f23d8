"""Build ROS messages of a rosbags typestore: ``make(store, type, **fields)`` fills every field
not given with its zero value (nested messages included), so a caller names only what it sets.
Also the common headers and poses of the project's frames (metres, 4x4 ``T_a_b``)."""
from __future__ import annotations

import numpy as np

from common.ros.types import normalise_type

_NP = {"bool": np.bool_, "int8": np.int8, "uint8": np.uint8, "byte": np.uint8, "char": np.uint8,
       "int16": np.int16, "uint16": np.uint16, "int32": np.int32, "uint32": np.uint32, "int64": np.int64,
       "uint64": np.uint64, "float32": np.float32, "float64": np.float64}


def _zero(store, node):
    kind, desc = node
    k = int(kind)
    if k == 1:                                    # BASE
        name = desc[0]
        if name == "string":
            return ""
        if name == "bool":
            return False
        return 0.0 if name.startswith("float") else 0
    if k == 2:                                    # NAME (a nested message)
        return make(store, desc)
    sub, n = desc
    if int(sub[0]) == 1 and sub[1][0] in _NP:     # numeric ARRAY / SEQUENCE -> ndarray
        return np.zeros(n if k == 3 else 0, _NP[sub[1][0]])
    return [_zero(store, sub) for _ in range(n if k == 3 else 0)]


def make(store, typename: str, **fields):
    """A message of ``typename`` with ``fields`` set and the rest zero."""
    typename = normalise_type(typename)
    cls = store.types[typename]
    _, defs = store.fielddefs[typename]
    kw = {}
    for name, node in defs:
        kw[name] = fields.pop(name) if name in fields else _zero(store, node)
    if fields:
        raise TypeError(f"{typename} has no field {sorted(fields)[0]!r}")
    return cls(**kw)


def header(store, stamp_ns: int, frame_id: str = "", seq: int = 0):
    t = make(store, "builtin_interfaces/msg/Time", sec=int(stamp_ns // 1_000_000_000),
             nanosec=int(stamp_ns % 1_000_000_000))
    if "seq" in dict(store.fielddefs["std_msgs/msg/Header"][1]):
        return make(store, "std_msgs/msg/Header", seq=seq, stamp=t, frame_id=frame_id)
    return make(store, "std_msgs/msg/Header", stamp=t, frame_id=frame_id)


def pose(store, T: np.ndarray, scale: float = 1.0):
    """A geometry_msgs/Pose of 4x4 ``T`` with the position divided by ``scale`` (metres per unit)."""
    from common.ros.conventions import T_to_pose_fields
    p, q = T_to_pose_fields(np.asarray(T, float), scale)
    return make(store, "geometry_msgs/msg/Pose",
                position=make(store, "geometry_msgs/msg/Point", x=float(p[0]), y=float(p[1]), z=float(p[2])),
                orientation=make(store, "geometry_msgs/msg/Quaternion", x=float(q[0]), y=float(q[1]),
                                 z=float(q[2]), w=float(q[3])))


def image(store, stamp_ns: int, img: np.ndarray, encoding: str = "bgr8", frame_id: str = "", seq: int = 0):
    """sensor_msgs/Image of a BGR array in ``encoding`` (see common.ros.images.bgr_to_raw)."""
    from common.ros.images import bgr_to_raw
    raw = bgr_to_raw(img, encoding)
    h, w = img.shape[:2]
    return make(store, "sensor_msgs/msg/Image", header=header(store, stamp_ns, frame_id, seq), height=h, width=w,
                encoding=encoding, is_bigendian=0, step=len(raw) // h, data=np.frombuffer(raw, np.uint8))


def compressed_image(store, stamp_ns: int, img: np.ndarray, fmt: str = "jpeg", quality: int = 95,
                     frame_id: str = "", seq: int = 0):
    """sensor_msgs/CompressedImage (JPEG or PNG of the BGR image, format as image_transport writes it)."""
    import cv2
    ok, buf = cv2.imencode(".jpg" if fmt == "jpeg" else ".png", img,
                           [cv2.IMWRITE_JPEG_QUALITY, quality] if fmt == "jpeg" else [])
    if not ok:
        raise ValueError(f"could not encode {fmt}")
    return make(store, "sensor_msgs/msg/CompressedImage", header=header(store, stamp_ns, frame_id, seq),
                format=f"bgr8; {fmt} compressed bgr8", data=buf.reshape(-1))


def camera_info(store, stamp_ns: int, K, dist, size, frame_id: str = "", P=None):
    """sensor_msgs/CameraInfo (plumb_bob with 5 coefficients, rational_polynomial with 8)."""
    K = np.asarray(K, float)
    D = np.asarray(dist, float).reshape(-1)
    if P is None:
        P = np.hstack([K, np.zeros((3, 1))])
    names = dict(store.fielddefs["sensor_msgs/msg/CameraInfo"][1])
    up = "K" in names
    kw = {("D" if up else "d"): D, ("K" if up else "k"): K.reshape(-1),
          ("R" if up else "r"): np.eye(3).reshape(-1), ("P" if up else "p"): np.asarray(P, float).reshape(-1)}
    return make(store, "sensor_msgs/msg/CameraInfo", header=header(store, stamp_ns, frame_id),
                width=int(size[0]), height=int(size[1]),
                distortion_model="plumb_bob" if len(D) <= 5 else "rational_polynomial", **kw)

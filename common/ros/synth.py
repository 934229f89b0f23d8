"""Bags in the robots' conventions from the project's own dataset folders (for tests, figures,
and to check a converter end to end), and the distorted twin of a pinhole dataset.

``dataset_to_bag(ds, out, convention)`` writes:

- ``ambf``: ROS 1 ``.bag`` as the 2021-22 AMBF challenge publishes it: ``rgb8`` images on
  ``/ambf/env/cameras/camera{L,R}/ImageData``, ``ambf_msgs/RigidBodyState`` of the CameraFrame
  (= the dataset's ECM frame) and the Needle (AMBF needle body frame), ``ambf_msgs/CameraState``
  of both cameras (AMBF camera axes, pose in the CameraFrame), all positions in ``unit``
  (default ``dm``: the challenge's decimetres). No camera_info: the dataset must be a
  fovy-1.2 pinhole rig. A folder's ``instruments`` become the challenge's CRTK wrapper topics
  ``/CRTK/psm{n}/measured_cp`` (PoseStamped in the arm's base, metres) and
  ``/CRTK/psm{n}/jaw/measured_js``, with the base body's ``/ambf/env/psm{n}/baselink/State``
  (``PSM_BASES``, in ``unit``).
- ``dvrk``: ROS 2 bag (MCAP by default) as a dVRK records it: ``/<rig>/{left,right}/image_raw``
  (``bgr8``) with ``camera_info`` (K, D plumb_bob), ``/ECM/measured_js`` (JointState),
  ``/ECM/measured_cp`` (PoseStamped, T_world_ecm), and, the dVRK having none, the needle's ground
  truth on ``/needle/measured_cp`` (PoseStamped, dataset needle frame); ``T_ecm_cam`` goes to a
  registration file ``<out>.registration.yaml`` with a topic map ``<out>.topics.yaml`` beside it.
  A folder's ``instruments`` (``psm1``, ``psm2``) become ``/PSM{n}/measured_cp`` (PoseStamped: the
  jaw frame in the arm's base, ``PSM_BASES``) and ``/PSM{n}/jaw/measured_js`` (JointState, the
  jaw angle), with the arms' registration ``<out>.psm_registration.yaml`` (T_world_base per arm).
``compressed=True`` writes ``sensor_msgs/CompressedImage`` (JPEG) on ``.../compressed`` instead.
"""
from __future__ import annotations

import os

import numpy as np
import yaml

from common.frames import CAMERAS
from common.geometry.transforms import inv_T
from common.ros import build
from common.ros.conventions import F_AMBF_CAM, T_AMBF_NEEDLE, unit_scale
from common.ros.types import typestore

AMBF_TOPICS = {"left": "/ambf/env/cameras/cameraL", "right": "/ambf/env/cameras/cameraR"}
DVRK_RIG = "jhu_daVinci"
DVRK_JOINTS = ["outer_yaw", "outer_pitch", "insertion", "outer_roll"]
PSM_BASES = {   # where the synthetic dVRK's arms stand: T_world_base (world = the ECM base), metres
    "psm1": np.array([[0.0, -1.0, 0.0, -0.18], [1.0, 0.0, 0.0, -0.02], [0.0, 0.0, 1.0, 0.21], [0, 0, 0, 1.0]]),
    "psm2": np.array([[0.0, 1.0, 0.0, 0.18], [-1.0, 0.0, 0.0, -0.03], [0.0, 0.0, 1.0, 0.19], [0, 0, 0, 1.0]]),
}
STAMP_BASE_NS = 1_700_000_000 * 1_000_000_000   # bag stamps = this + the dataset's stamp_ns (ROS time 0 means unset)


def _rigid_body_state(store, stamp, T, scale, name):
    return build.make(store, "ambf_msgs/msg/RigidBodyState", header=build.header(store, stamp, "World"),
                      name=build.make(store, "std_msgs/msg/String", data=name),
                      pose=build.pose(store, T, scale))


def _camera_state(store, stamp, T, scale, name):
    return build.make(store, "ambf_msgs/msg/CameraState", header=build.header(store, stamp, "CameraFrame"),
                      parent_name=build.make(store, "std_msgs/msg/String", data="CameraFrame"),
                      name=build.make(store, "std_msgs/msg/String", data=name),
                      pose=build.pose(store, T, scale))


def _check_arm(dataset: str, name: str) -> None:
    if name not in PSM_BASES:
        raise ValueError(f"{dataset}: instrument {name!r}: the bags' conventions write psm1 and psm2")


def _jaw_state(store, stamp, jaw_rad: float):
    return build.make(store, "sensor_msgs/msg/JointState", header=build.header(store, stamp), name=["jaw"],
                      position=np.array([float(jaw_rad)]), velocity=np.zeros(1), effort=np.zeros(1))


class BagWriter:
    """One writer API over rosbags' ROS 1 and ROS 2 writers."""

    def __init__(self, path: str, ros: int, storage: str):
        self.ros = ros
        self.store = typestore(ros)
        if ros == 1:
            from rosbags.rosbag1 import Writer
            self.w = Writer(path)
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer
            plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
            self.w = Writer(path, version=9, storage_plugin=plugin)
        self.w.open()
        self.conns = {}

    def write(self, topic: str, msg, stamp_ns: int) -> None:
        t = msg.__msgtype__
        if topic not in self.conns:
            self.conns[topic] = self.w.add_connection(topic, t, typestore=self.store)
        data = self.store.serialize_ros1(msg, t) if self.ros == 1 else self.store.serialize_cdr(msg, t)
        self.w.write(self.conns[topic], int(stamp_ns), data)

    def close(self):
        self.w.close()


def dataset_to_bag(dataset: str, out: str, convention: str, *, unit: str | None = None,
                   compressed: bool = False, encoding: str | None = None, storage: str = "mcap",
                   ros: int | None = None, max_frames: int = 0) -> dict:
    """Write the dataset folder as a bag in ``convention`` (ambf | dvrk); see the module docstring.
    Returns {bag, frames, topics_file (dvrk), registration (dvrk)}."""
    from common.data.dataset import Dataset
    ds = Dataset(dataset)
    rig = ds.rig
    if convention not in ("ambf", "dvrk"):
        raise ValueError(f"convention must be ambf or dvrk, got {convention!r}")
    ros = ros or (1 if convention == "ambf" else 2)
    unit = unit or ("dm" if convention == "ambf" else "m")
    scale = unit_scale(unit)
    if os.path.exists(out):
        raise ValueError(f"{out} exists; writers only create new bags")
    if convention == "ambf" and (np.any(rig.left.dist) or np.any(rig.right.dist)):
        raise ValueError(f"{dataset}: AMBF has no lens distortion and no camera_info: use a pinhole dataset")
    bag = BagWriter(out, ros, storage)
    store = bag.store
    frames = ds.frames[:max_frames] if max_frames else ds.frames
    enc = encoding or ("rgb8" if convention == "ambf" else "bgr8")
    result = {"bag": out, "frames": len(frames)}
    try:
        for i, fr in enumerate(frames):
            t = STAMP_BASE_NS + int(fr.stamp_ns)
            if convention == "ambf":
                if fr.T_world_ecm is not None:
                    bag.write("/ambf/env/CameraFrame/State",
                              _rigid_body_state(store, t, fr.T_world_ecm, scale, "CameraFrame"), t)
                for c in CAMERAS:
                    T_cf_cam = rig[c].T_ecm_cam @ F_AMBF_CAM        # AMBF camera axes
                    bag.write(AMBF_TOPICS[c] + "/State",
                              _camera_state(store, t, T_cf_cam, scale, "camera" + c[0].upper()), t)
                for name, inst in (fr.instruments or {}).items():
                    _check_arm(dataset, name)
                    bag.write(f"/ambf/env/{name}/baselink/State",
                              _rigid_body_state(store, t, PSM_BASES[name], scale, f"{name}/baselink"), t)
                    bag.write(f"/CRTK/{name}/measured_cp", build.make(
                        store, "geometry_msgs/msg/PoseStamped", header=build.header(store, t, f"{name}/baselink"),
                        pose=build.pose(store, inv_T(PSM_BASES[name]) @ inst.T_world_jaw)), t)
                    bag.write(f"/CRTK/{name}/jaw/measured_js", _jaw_state(store, t, inst.jaw_rad), t)
                    result.setdefault("instruments", set()).add(name)
                if fr.T_world_needle is not None:
                    bag.write("/ambf/env/Needle/State",
                              _rigid_body_state(store, t, fr.T_world_needle @ inv_T(T_AMBF_NEEDLE), scale,
                                                "Needle"), t)
            else:
                if fr.ecm_joints is not None:
                    js = build.make(store, "sensor_msgs/msg/JointState", header=build.header(store, t),
                                    name=list(DVRK_JOINTS), position=np.asarray(fr.ecm_joints, float),
                                    velocity=np.zeros(4), effort=np.zeros(4))
                    bag.write("/ECM/measured_js", js, t)
                if fr.T_world_ecm is not None:
                    bag.write("/ECM/measured_cp", build.make(store, "geometry_msgs/msg/PoseStamped",
                                                             header=build.header(store, t, "ECM_base"),
                                                             pose=build.pose(store, fr.T_world_ecm)), t)
                if fr.T_world_needle is not None:
                    bag.write("/needle/measured_cp", build.make(store, "geometry_msgs/msg/PoseStamped",
                                                                header=build.header(store, t, "ECM_base"),
                                                                pose=build.pose(store, fr.T_world_needle)), t)
                for name, inst in (fr.instruments or {}).items():
                    _check_arm(dataset, name)
                    arm = name.upper()
                    T_base_jaw = inv_T(PSM_BASES[name]) @ inst.T_world_jaw
                    bag.write(f"/{arm}/measured_cp", build.make(store, "geometry_msgs/msg/PoseStamped",
                                                               header=build.header(store, t, f"{arm}_base"),
                                                               pose=build.pose(store, T_base_jaw)), t)
                    bag.write(f"/{arm}/jaw/measured_js", _jaw_state(store, t, inst.jaw_rad), t)
                    result.setdefault("instruments", set()).add(name)
                for c in CAMERAS:
                    bag.write(f"/{DVRK_RIG}/{c}/camera_info",
                              build.camera_info(store, t, rig[c].K, rig[c].dist, ds.meta.image_size,
                                                f"{DVRK_RIG}_{c}"), t)
            for c in CAMERAS:
                img = ds.image(fr, c)
                base = AMBF_TOPICS[c] + "/ImageData" if convention == "ambf" else f"/{DVRK_RIG}/{c}/image_raw"
                if compressed:
                    bag.write(base + "/compressed", build.compressed_image(store, t, img, "jpeg", 95, c, i), t)
                else:
                    bag.write(base, build.image(store, t, img, enc, c, i), t)
    finally:
        bag.close()
    if convention == "ambf" and result.get("instruments"):
        result["instruments"] = sorted(result["instruments"])
    if convention == "dvrk":
        reg = out.rstrip("/") + ".registration.yaml"
        with open(reg, "w") as f:
            yaml.safe_dump({"T_ecm_cam": {c: rig[c].T_ecm_cam.tolist() for c in CAMERAS}}, f)
        tm = out.rstrip("/") + ".topics.yaml"
        topic_map = {"preset": "dvrk", "registration": os.path.basename(reg), "needle_pose": "/needle/measured_cp",
                     "needle": ds.needle.to_dict()}
        if result.get("instruments"):
            psm_reg = out.rstrip("/") + ".psm_registration.yaml"
            with open(psm_reg, "w") as f:
                yaml.safe_dump({"T_world_base": {n: PSM_BASES[n].tolist() for n in sorted(result["instruments"])}}, f)
            topic_map["instrument_registration"] = os.path.basename(psm_reg)
            result["psm_registration"] = psm_reg
            result["instruments"] = sorted(result["instruments"])
        with open(tm, "w") as f:
            yaml.safe_dump(topic_map, f)
        result.update(registration=reg, topics_file=tm)
    return result


# ---------------------------------------------------------------- distorted twin

def distortion_maps(K: np.ndarray, dist: np.ndarray, size) -> tuple[np.ndarray, np.ndarray]:
    """(map_x, map_y) float32: for each pixel of a distorted image, where it lies in the pinhole
    image of the same K (cv2.remap(pinhole, map_x, map_y) renders the distorted image)."""
    import cv2
    w, h = int(size[0]), int(size[1])
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pts = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    ideal = cv2.undistortPoints(pts, K, dist, None, None, K,
                                (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10))
    ideal = ideal.reshape(h, w, 2).astype(np.float32)
    return ideal[..., 0], ideal[..., 1]


def distort_dataset(src: str, out: str, dist, image_format: str = "png", progress: bool = False) -> int:
    """Write ``out``: the dataset ``src`` (a pinhole rig) seen through lens distortion ``dist``
    (OpenCV k1, k2, p1, p2[, k3], same K) in both cameras: images resampled, keypoints and boxes
    projected with the distortion. Returns the number of frames."""
    import cv2

    from common.data.dataset import Dataset, DatasetMeta, Frame
    from common.data.writer import DatasetWriter
    from common.geometry.camera import StereoRig
    from common.geometry.oracle import arc_bbox, true_keypoints
    ds = Dataset(src)
    if np.any(ds.rig.left.dist) or np.any(ds.rig.right.dist):
        raise ValueError(f"{src}: already distorted; give a pinhole dataset")
    cams = ds.rig.to_dict()
    for c in CAMERAS:
        cams[c]["dist"] = [float(x) for x in dist]
    rig = StereoRig.from_dict(cams, ds.meta.image_size)
    meta = DatasetMeta(ds.meta.image_size, rig, ds.needle, ds.arm,
                       source=f"distorted twin of {os.path.basename(os.path.abspath(src))}, dist {list(dist)}")
    maps = {c: distortion_maps(rig[c].K, rig[c].dist, ds.meta.image_size) for c in CAMERAS}
    it = ds.frames
    if progress:
        from common.progress import progress_bar
        it = progress_bar(it, desc="distort", unit="frame")
    with DatasetWriter(out, meta, image_format=image_format) as w:
        for fr in it:
            imgs = {c: cv2.remap(ds.image(fr, c), *maps[c], cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
                    for c in CAMERAS}
            paths = w.write_images(fr.index, imgs)
            nf = Frame(index=fr.index, stamp_ns=fr.stamp_ns, left=paths["left"], right=paths["right"],
                       sequence=fr.sequence, step=fr.step, ecm_joints=fr.ecm_joints, T_world_ecm=fr.T_world_ecm,
                       T_world_needle=fr.T_world_needle)
            if fr.T_ecm_needle is not None:
                kp, vis, box = {}, {}, {}
                for c in CAMERAS:
                    kp[c], v = true_keypoints(rig[c], fr.T_ecm_needle, ds.needle)
                    # occlusion as the source had it, and inside the distorted image
                    vis[c] = v & (fr.visible[c] if fr.visible is not None else True)
                    b = arc_bbox(rig[c], fr.T_ecm_needle, ds.needle)
                    box[c] = None if b is None else b.tolist()
                if all(np.all(np.isfinite(kp[c])) for c in CAMERAS):
                    nf.keypoints, nf.visible, nf.bbox = kp, vis, box
            w.append(nf)
    return len(ds.frames)

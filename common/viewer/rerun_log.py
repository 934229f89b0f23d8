"""What the viewer logs to Rerun (``rerun-sdk``, the ``viewer`` extra): one function per thing
shown, each taking an explicit ``rerun.RecordingStream``. Used by the live viewer node and by
``needletrack eval --rrd``.

Entity tree (3D in metres, the world frame of the ECM's kinematics)::

    world/ecm                   Transform3D T_world_ecm (per frame)
    world/ecm/{left,right}      Transform3D T_ecm_cam + Pinhole (the frusta; image downscaled)
    world/ecm/{left,right}/image   the Fig. 1 picture (JPEG)
    world/ecm/needle/<method>   the needle's arc at that method's pose (LineStrips3D)
    world/ecm/needle/truth      the true arc, when known
    world/ecm_path              the ECM's path (its origin over the recent frames)
    plots/<series>/<line>       Scalars: pos_err_mm, rot_err_deg, rate_hz, latency_ms, confidence

Timelines: ``seq`` (frame number) and ``time`` (the frame's stamp).
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from common.frames import CAMERAS
from common.geometry.transforms import transform_points
from common import palette


def blueprint():
    """The default layout: 3D view, the two camera pictures, the error/rate/latency plots."""
    import rerun.blueprint as rrb
    return rrb.Blueprint(rrb.Horizontal(
        rrb.Vertical(rrb.Spatial2DView(origin="world/ecm/left", name="left"),
                     rrb.Spatial2DView(origin="world/ecm/right", name="right")),
        rrb.Spatial3DView(origin="world", name="3D"),
        rrb.Vertical(*(rrb.TimeSeriesView(origin=f"plots/{k}", name=k) for k in
                       ("pos_err_mm", "rot_err_deg", "rate_hz", "latency_ms", "confidence"))),
        column_shares=[2, 2, 1]), collapse_panels=True)


def new_recording(app_id: str = "needletrack", recording_id: Optional[str] = None):
    """A fresh recording stream (not the global one)."""
    import rerun as rr
    return rr.RecordingStream(app_id, recording_id=recording_id)


def set_sinks(rec, grpc_port: Optional[int] = None, save: Optional[str] = None,
              memory_limit: str = "256MiB") -> Optional[str]:
    """Send ``rec`` to an in-process gRPC server on 127.0.0.1:``grpc_port`` (its ``rerun+http``
    URL is returned) and/or record it to the file ``save`` (.rrd)."""
    import rerun as rr
    sinks, url = [], None
    if grpc_port is not None:
        sinks.append(rr.GrpcServerSink(bind_ip="127.0.0.1", port=int(grpc_port),
                                       server_memory_limit=memory_limit))
        url = f"rerun+http://127.0.0.1:{grpc_port}/proxy"
    if save:
        sinks.append(rr.FileSink(str(save)))
    if sinks:
        rec.set_sinks(*sinks, default_blueprint=blueprint())
    return url


def log_rig(rec, rig, scale: float) -> None:
    """The two cameras (static): their pose in the ECM frame and pinhole at image ``scale``."""
    import rerun as rr
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    for name in CAMERAS:
        cam = rig[name]
        K = np.array(cam.K, float).copy()
        K[:2, :2] *= scale
        K[:2, 2] = (K[:2, 2] + 0.5) * scale - 0.5
        rec.log(f"world/ecm/{name}", rr.Transform3D(translation=cam.T_ecm_cam[:3, 3],
                                                    mat3x3=cam.T_ecm_cam[:3, :3]), static=True)
        rec.log(f"world/ecm/{name}", rr.Pinhole(image_from_camera=K,
                                                resolution=[round(cam.width * scale), round(cam.height * scale)],
                                                camera_xyz=rr.ViewCoordinates.RDF,
                                                image_plane_distance=0.03), static=True)


def set_frame(rec, seq: int, stamp_ns: int) -> None:
    """Put the following logs on frame ``seq`` at ``stamp_ns`` (ns)."""
    rec.set_time("seq", sequence=int(seq))
    rec.set_time("time", timestamp=int(stamp_ns) * 1e-9)


def log_image(rec, camera: str, jpeg: bytes) -> None:
    import rerun as rr
    rec.log(f"world/ecm/{camera}/image", rr.EncodedImage(contents=jpeg, media_type="image/jpeg"))


def log_ecm(rec, T_world_ecm: np.ndarray, path_world: Optional[np.ndarray] = None) -> None:
    """The ECM's pose, and its path (N, 3) world points (m) when given."""
    import rerun as rr
    T = np.asarray(T_world_ecm, float)
    rec.log("world/ecm", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
    if path_world is not None and len(path_world) >= 2:
        rec.log("world/ecm_path", rr.LineStrips3D([np.asarray(path_world, float)], colors=[[200, 200, 200]]))


def log_needle(rec, name: str, arc_needle: np.ndarray, T_ecm_needle: np.ndarray,
               ambiguous: bool = False) -> None:
    """The needle's arc (needle-frame points, m) at ``T_ecm_needle`` as ``world/ecm/needle/<name>``
    (``truth``: green; a method: its colour, ``common.palette``; ambiguous poses thinner)."""
    import rerun as rr
    colour = list(palette.rgb(palette.TRUTH if name == "truth" else palette.method(name)))
    pts = transform_points(np.asarray(T_ecm_needle, float), arc_needle)
    rec.log(f"world/ecm/needle/{name}",
            rr.LineStrips3D([pts], colors=[colour], radii=[0.0002 if ambiguous else 0.0004]))


_STYLED: set = set()     # (recording id, entity path) whose line colour is logged


def log_scalar(rec, series: str, line: str, value: float) -> None:
    """``value`` on ``plots/<series>/<line>``; a method's line gets its colour (once, static)."""
    import rerun as rr
    path = f"plots/{series}/{line}"
    key = (rec.get_recording_id(), path)
    if key not in _STYLED:
        _STYLED.add(key)
        colour = list(palette.rgb(palette.line(line)))
        rec.log(path, rr.SeriesLines(colors=[colour], names=[line]), static=True)
    rec.log(path, rr.Scalars(float(value)))

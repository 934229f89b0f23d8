"""ROS image messages <-> (h, w, 3) uint8 BGR arrays.

``sensor_msgs/Image`` encodings read: ``bgr8``, ``rgb8``, ``bgra8``, ``rgba8``, ``mono8``,
``mono16`` (scaled to 8 bits), ``bayer_rggb8``, ``bayer_bggr8``, ``bayer_gbrg8``,
``bayer_grbg8`` (demosaiced as cv_bridge does); rows may be padded (``step``).
``sensor_msgs/CompressedImage``: JPEG or PNG whatever ``format`` says (the file's own header
decides; its stated size is checked, with the codec's ``image_header_size``, before anything is
decoded: a small PNG claiming 20000x20000 px is never inflated). Sides at most the codec's
``MAX_IMAGE_SIDE``. Anything else raises ``ImageError`` naming the encoding and where the message
came from; ``image_problem`` says the same without decoding.
"""
from __future__ import annotations

import cv2
import numpy as np

from common.errors import NeedletrackError
from common.runtime.messages import MAX_IMAGE_SIDE, image_header_size

ENCODINGS = ("bgr8", "rgb8", "bgra8", "rgba8", "mono8", "mono16", "bayer_rggb8", "bayer_bggr8",
             "bayer_gbrg8", "bayer_grbg8")
_CHANNELS = {"bgr8": 3, "rgb8": 3, "bgra8": 4, "rgba8": 4, "mono8": 1, "mono16": 1,
             "bayer_rggb8": 1, "bayer_bggr8": 1, "bayer_gbrg8": 1, "bayer_grbg8": 1}
# ROS's Bayer names give the top-left 2x2 pattern; OpenCV names the second row's pattern
# (cv_bridge's table).
_BAYER = {"bayer_rggb8": cv2.COLOR_BayerBG2BGR, "bayer_bggr8": cv2.COLOR_BayerRG2BGR,
          "bayer_gbrg8": cv2.COLOR_BayerGR2BGR, "bayer_grbg8": cv2.COLOR_BayerGB2BGR}


class ImageError(NeedletrackError, ValueError):
    """An image message that cannot be turned into pixels; the text says which and why."""


def is_compressed(msg) -> bool:
    return hasattr(msg, "format") and not hasattr(msg, "encoding")


def image_problem(msg) -> str | None:
    """What makes an Image or CompressedImage message unusable, read from its fields and (for a
    compressed one) the file header only, without decoding; None when it is fine."""
    if is_compressed(msg):
        size = image_header_size(msg.data)
        if size is None:
            return f"CompressedImage: format {msg.format!r}: not a decodable JPEG/PNG (no header, {len(msg.data)} bytes)"
        if not (1 <= size[0] <= MAX_IMAGE_SIDE and 1 <= size[1] <= MAX_IMAGE_SIDE):
            return (f"CompressedImage: the {msg.format!r} header says {size[0]}x{size[1]} px; sides must be "
                    f"in 1..{MAX_IMAGE_SIDE}")
        return None
    enc = str(msg.encoding).lower()
    if enc not in _CHANNELS:
        return f"Image: encoding {msg.encoding!r} is not supported (supported: {', '.join(ENCODINGS)})"
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    need = w * _CHANNELS[enc] * (2 if enc == "mono16" else 1)
    if not (1 <= w <= MAX_IMAGE_SIDE and 1 <= h <= MAX_IMAGE_SIDE):
        return f"Image: {w}x{h} {enc}: sides must be in 1..{MAX_IMAGE_SIDE}"
    if step < need or len(msg.data) < step * h:
        return f"Image: {w}x{h} {enc} with step {step} needs {step * h} bytes, got {len(msg.data)}"
    return None


def image_to_bgr(msg, where: str = "") -> np.ndarray:
    """A deserialised ``sensor_msgs/Image`` or ``CompressedImage`` as an (h, w, 3) uint8 BGR array."""
    at = f" ({where})" if where else ""
    why = image_problem(msg)
    if why is not None:
        kind, _, rest = why.partition(":")
        raise ImageError(f"{kind}{at}:{rest}")
    if is_compressed(msg):
        data = np.frombuffer(bytes(msg.data), np.uint8)
        try:
            img = cv2.imdecode(data, cv2.IMREAD_COLOR)
        except cv2.error as exc:
            raise ImageError(f"CompressedImage{at}: corrupt: {str(exc).strip()[:200]}") from None
        if img is None:
            raise ImageError(f"CompressedImage{at}: format {msg.format!r}: not a decodable JPEG/PNG "
                             f"({len(data)} bytes)")
        return img
    enc = str(msg.encoding).lower()
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    ch = _CHANNELS[enc]
    bpp = 2 if enc == "mono16" else 1
    data = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    rows = data[: step * h].reshape(h, step)[:, : w * ch * bpp]
    if enc == "mono16":
        dt = ">u2" if msg.is_bigendian else "<u2"
        img16 = np.frombuffer(rows.tobytes(), dt).reshape(h, w)
        return cv2.cvtColor((img16 >> 8).astype(np.uint8), cv2.COLOR_GRAY2BGR)
    img = rows.reshape(h, w, ch) if ch > 1 else rows.reshape(h, w)
    if enc == "bgr8":
        return np.ascontiguousarray(img)
    if enc == "rgb8":
        return cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    if enc == "bgra8":
        return cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    if enc == "rgba8":
        return cv2.cvtColor(img, cv2.COLOR_RGBA2BGR)
    if enc == "mono8":
        return cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_GRAY2BGR)
    return cv2.cvtColor(np.ascontiguousarray(img), _BAYER[enc])


def bgr_to_raw(img: np.ndarray, encoding: str) -> bytes:
    """The pixel bytes of a ``sensor_msgs/Image`` in ``encoding`` (bgr8, rgb8, mono8 or a
    bayer_* mosaic sampled from the BGR image) with step = width * channels."""
    if encoding == "bgr8":
        return np.ascontiguousarray(img).tobytes()
    if encoding == "rgb8":
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB).tobytes()
    if encoding == "mono8":
        return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY).tobytes()
    if encoding in _BAYER:
        pattern = encoding[6:10]          # e.g. "rggb": colours of (0,0), (0,1), (1,0), (1,1)
        idx = {"b": 0, "g": 1, "r": 2}
        out = np.empty(img.shape[:2], np.uint8)
        for k, (dy, dx) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
            out[dy::2, dx::2] = img[dy::2, dx::2, idx[pattern[k]]]
        return out.tobytes()
    raise ImageError(f"cannot write encoding {encoding!r}")

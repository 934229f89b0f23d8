"""ROS image encodings -> BGR (common/ros/images.py)."""
import numpy as np
import pytest

from common.ros import build
from common.ros.images import ImageError, image_to_bgr
from common.ros.types import typestore


@pytest.fixture(scope="module")
def img():
    rng = np.random.default_rng(0)
    base = rng.integers(0, 255, (6, 8, 3), dtype=np.uint8)
    return np.kron(base, np.ones((8, 8, 1), np.uint8))        # 48x64, smooth blocks


@pytest.mark.parametrize("ros", [1, 2])
@pytest.mark.parametrize("enc", ["bgr8", "rgb8"])
def test_colour_encodings_round_trip_exactly(img, enc, ros):
    msg = build.image(typestore(ros), 1, img, enc)
    assert np.array_equal(image_to_bgr(msg), img)


def test_mono_and_padded_rows(img):
    st = typestore(2)
    msg = build.image(st, 1, img, "mono8")
    out = image_to_bgr(msg)
    assert out.shape == img.shape and np.all(out[..., 0] == out[..., 1])
    # rows padded to a step of width + 16 bytes
    raw = np.frombuffer(msg.data, np.uint8).reshape(48, 64)
    padded = np.hstack([raw, np.full((48, 16), 7, np.uint8)])
    msg2 = build.make(st, "sensor_msgs/msg/Image", header=msg.header, height=48, width=64, encoding="mono8",
                      step=80, data=padded.reshape(-1))
    assert np.array_equal(image_to_bgr(msg2), out)


@pytest.mark.parametrize("enc", ["bayer_rggb8", "bayer_bggr8", "bayer_gbrg8", "bayer_grbg8"])
def test_bayer_patterns_demosaic_to_the_right_colours(img, enc):
    out = image_to_bgr(build.image(typestore(2), 1, img, enc))
    inner = (slice(4, -4), slice(4, -4))
    # away from block edges the demosaiced colour is the block's colour (a wrong pattern swaps R/B)
    err = np.abs(out.astype(int) - img)[inner]
    assert np.median(err) <= 2, enc


def test_compressed_png_is_exact_and_garbage_is_refused(img):
    st = typestore(2)
    assert np.array_equal(image_to_bgr(build.compressed_image(st, 1, img, "png")), img)
    bad = build.make(st, "sensor_msgs/msg/CompressedImage", format="jpeg", data=np.zeros(10, np.uint8))
    with pytest.raises(ImageError, match="not a decodable JPEG/PNG"):
        image_to_bgr(bad, "/cam/left")


def test_unknown_encoding_and_short_data_name_the_problem(img):
    st = typestore(2)
    msg = build.make(st, "sensor_msgs/msg/Image", height=2, width=2, encoding="32FC1", step=8,
                     data=np.zeros(16, np.uint8))
    with pytest.raises(ImageError, match=r"/cam/left\): encoding '32FC1' is not supported"):
        image_to_bgr(msg, "/cam/left")
    msg = build.make(st, "sensor_msgs/msg/Image", height=4, width=4, encoding="rgb8", step=12,
                     data=np.zeros(20, np.uint8))
    with pytest.raises(ImageError, match="needs 48 bytes, got 20"):
        image_to_bgr(msg)

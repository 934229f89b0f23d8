"""The one schema mechanism (common/runtime/schema.py): fields declared once with their
constraints, converted strictly by msgspec, refused in placed words."""
from dataclasses import dataclass
from typing import Annotated, Optional

import msgpack
import msgspec
import numpy as np
import pytest

from common.runtime.messages import Keypoints, MessageError, decode
from common.runtime.params import ParamError, param_errors, parse_params
from common.runtime.schema import Array, Says, fields_of


def _payload(cls, body):
    return msgpack.packb({"schema": cls.SCHEMA, "version": cls.VERSION, "body": body})


def _keypoints_body(**change):
    body = {"camera": "left", "seq": 1, "stamp_ns": 2, "found": True, "uv": [[1.0, 2.0]] * 5,
            "scores": [1.0] * 5, "confidence": 0.9, "detector": "x"}
    return {**body, **change}


def test_a_python_default_is_not_a_wire_default_and_optional_fields_may_be_absent():
    assert decode(_payload(Keypoints, _keypoints_body())).detector == "x"
    body = _keypoints_body()
    del body["detector"]                       # a default in Python (""), required on the wire
    with pytest.raises(MessageError, match="Keypoints.detector: missing"):
        decode(_payload(Keypoints, body))
    optional = {f.name for f in fields_of(Keypoints) if f.optional}
    assert "reason" in optional and "epoch" in optional and "detector" not in optional


@pytest.mark.parametrize("change,text", [
    ({"end_identity": 1.5}, r"Keypoints.end_identity: must be a probability in \[0, 1\], got 1.5"),
    ({"seq": -4}, "Keypoints.seq: must not be negative, got -4"),
    ({"seq": 2 ** 63}, "Keypoints.seq: out of the int64 range"),
    ({"camera": "middle"}, r"Keypoints.camera: must be one of \('left', 'right'\), got 'middle'"),
    ({"confidence": "high"}, "Keypoints.confidence: expected number, got str"),
    ({"confidence": None}, "Keypoints.confidence: required, got null"),
    ({"uv": [[1.0, 2.0]] * 4}, r"Keypoints.uv: expected shape \(5, 2\), got \(4, 2\)"),
    # several faults: a type error anywhere before a constraint, the sign before other constraints
    ({"end_identity": 1.5, "seq": -1, "unfamiliarity": "x"}, "Keypoints.unfamiliarity: expected number, got str"),
    ({"end_identity": 1.5, "epoch": -1}, "Keypoints.epoch: must not be negative"),
])
def test_constraints_on_the_fields_are_refused_in_placed_words(change, text):
    with pytest.raises(MessageError, match=text):
        decode(_payload(Keypoints, _keypoints_body(**change)))


def test_arrays_keep_their_dtype_and_plain_lists_are_taken():
    k = decode(_payload(Keypoints, _keypoints_body()))
    assert type(k.uv) is np.ndarray and k.uv.dtype == np.float64 and k.uv.shape == (5, 2)
    assert isinstance(k.uv, Array[5, 2]) and not isinstance([1.0], Array[5, 2])


@dataclass
class _Params:
    rate_hz: Annotated[float, msgspec.Meta(gt=0), Says("must be positive (Hz), got {value}")] = 30.0
    window: Annotated[int, msgspec.Meta(ge=1)] = 4
    names: tuple[str, ...] = ()
    scale: Optional[float] = None


def test_params_take_constraints_on_the_field_and_keep_did_you_mean():
    p = parse_params(_Params, {"rate_hz": 60, "names": ["a", "b"], "scale": 2})
    assert p.rate_hz == 60.0 and type(p.rate_hz) is float and p.names == ("a", "b") and type(p.scale) is float
    assert param_errors(_Params, {"rate_hz": -1, "window": 0, "scale": float("inf"), "windw": 3}, "n.params") == [
        "n.params.rate_hz: must be positive (Hz), got -1",
        "n.params.window: expected `int` >= 1, got 0",
        "n.params.scale: expected number or null, got inf",
        "n.params.windw: unknown param (did you mean 'window'?)"]
    with pytest.raises(ParamError, match="rate_hz: expected number, got 'fast'"):
        parse_params(_Params, {"rate_hz": "fast"})


def test_the_graph_file_is_checked_from_its_declared_fields():
    from common.runtime.graph import NodeSpec, ZenohSettings
    from common.runtime.graph_checks import validate_graph
    from common.runtime.schema import file_keys
    assert file_keys(ZenohSettings) == ["connect", "listen", "mode", "open", "shm_pool_mb", "tls"]  # not run_credentials
    assert "feedback" in file_keys(NodeSpec)
    doc = {"graph": "g", "zenoh": {"mode": "mesh", "shm_pool_mb": -1, "tls": {"ca": "", "cert": "c.pem"}},
           "nodes": [{"id": "cmd", "command": [], "restart": None, "spare": 1, "inputs": 5, "feedback": ["x"]}]}
    assert validate_graph(doc) == [
        "zenoh.mode: must be one of peer, client, router; got 'mesh'",
        "zenoh.tls.ca: expected a file path, got ''",
        "zenoh.tls.cert: must contain '{id}' (each node, and the launcher, has its own certificate: "
        "e.g. 'certs/{id}.pem'); got 'c.pem'",
        "zenoh.tls.key: missing (a PEM file path, with {id})",
        "zenoh.shm_pool_mb: expected a non-negative int, got -1",
        "nodes[0].id: must be a name of letters, digits, '_', '-', '.'; got 'cmd'",
        "nodes[0].command: expected a non-empty list of strings, got []",
        "nodes[0].restart: must be one of never, on-failure, always; got None",
        "nodes[0].spare: expected true or false, got 1",
        "nodes[0].feedback: expected a list of this node's input names, got ['x']",   # inputs: 5 crashed this check
        "nodes[0].inputs: expected a map of input name -> 'node/output', got int"]


def test_dataset_yaml_is_read_from_its_declared_sections():
    import yaml

    from common.data.meta import DatasetError, DatasetMeta, MetaYaml, parse_meta
    from common.geometry.camera import StereoRig
    from common.geometry.needle import NeedleModel
    from common.runtime.schema import fields_of
    assert [f.name for f in fields_of(MetaYaml)] == ["format", "version", "image_size", "cameras", "needle", "ecm"]
    d = DatasetMeta((640, 480), StereoRig.default(640, 480), NeedleModel(), None, "x").to_dict()
    assert parse_meta(yaml.safe_dump(d)).image_size == (640, 480)
    d["cameras"]["right"]["dist"] = [0.1] * 3
    with pytest.raises(DatasetError, match=r"dataset.yaml:\d+: cameras.right.dist: OpenCV distortion needs 4, 5"):
        parse_meta(yaml.safe_dump(d))
    d["needle"]["radius_m"] = -0.01
    with pytest.raises(DatasetError, match="cameras.right.dist"):        # the first in declared order
        parse_meta(yaml.safe_dump(d))
    del d["cameras"]["right"]["dist"], d["needle"]["keypoint_angles_deg"]
    with pytest.raises(DatasetError, match="needle.radius_m: must be positive, got -0.01"):
        parse_meta(yaml.safe_dump(d))
    d["needle"]["radius_m"] = 0.01
    with pytest.raises(DatasetError, match="needle.keypoint_angles_deg: required field missing"):
        parse_meta(yaml.safe_dump(d))

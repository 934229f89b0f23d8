"""Instrument kinds of the ``random`` looks: each kind is a list of primitive parts (boxes,
cylinders, capsules, spheres) on the instrument's body and on its two jaws.

Frames as in ``common.sim.scene.Instrument``: the body's z runs up the shaft from near the jaw
tips, the jaws turn about x at the pivot ``JAW_PIVOT_M`` up the shaft; a jaw's parts are given in
its own body (origin at the pivot, the jaw hanging along -z, lying on +y of the closed jaws'
plane); the other jaw is their mirror image in y. Lengths in m, sizes as MuJoCo's ``geom size``
(half-lengths; a cylinder's or capsule's axis is its local z), rotations as rotation vectors (rad).

A part's ``role`` picks its slot's material: ``shaft``, ``jaw`` (metal of the jaws and wrist) or
``insert`` (carbide inserts, teeth, insulation, a clip: a second finish). Kinds without jaws
(``hook``, ``suction``) leave the jaw bodies empty. Which kinds the training looks use and which
are held out: ``common.sim.random_looks.POOLS``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

JAW_PIVOT_M = 0.0045        # common.sim.scene.JAW_PIVOT_M (scene imports this module)
SHAFT_TOP_M = 0.25
WRIST_TOP_M = 0.011
BODY_PARTS = 8              # part slots on an instrument's body
JAW_PARTS = 5               # part slots on each jaw


@dataclass(frozen=True)
class Part:
    """One primitive: MuJoCo geom ``kind``, ``size``, ``pos`` and rotation vector ``rot`` in its body."""

    kind: str
    size: tuple
    pos: tuple
    rot: tuple = (0.0, 0.0, 0.0)
    role: str = "jaw"

    def mirrored(self) -> "Part":
        """The part reflected in the plane y = 0 (the other jaw)."""
        r = self.rot
        return Part(self.kind, self.size, (self.pos[0], -self.pos[1], self.pos[2]), (-r[0], r[1], -r[2]), self.role)


ALONG_X = (0.0, np.pi / 2, 0.0)


def _body(shaft_r: float, wrist_r: float, wrist_top: float = WRIST_TOP_M) -> list[Part]:
    """Shaft, wrist and the jaws' pin, as every kind with jaws has them."""
    return [Part("cylinder", (shaft_r, (SHAFT_TOP_M - wrist_top) / 2, 0), (0, 0, (SHAFT_TOP_M + wrist_top) / 2),
                 role="shaft"),
            Part("cylinder", (wrist_r, (wrist_top - JAW_PIVOT_M) / 2, 0), (0, 0, (wrist_top + JAW_PIVOT_M) / 2)),
            Part("cylinder", (0.0011, wrist_r * 0.9, 0), (0, 0, JAW_PIVOT_M), ALONG_X)]


def _teeth(n: int, half_w: float, z0: float, z1: float, y: float) -> list[Part]:
    """Serrations across the jaw's inner face from z0 to z1 (jaw frame)."""
    return [Part("box", (half_w, 0.00012, 0.00014), (0, y, z), role="insert") for z in np.linspace(z0, z1, n)]


def _chain(kind: str, segments, y: float, role: str = "jaw") -> list[Part]:
    """Parts end to end from the pivot, bending towards +x: ``segments`` of (length, angle from -z
    in rad, half-width, half-thickness); capsules take the half-width as their radius."""
    out, p = [], np.zeros(3)
    for length, a, hw, ht in segments:
        d = np.array([np.sin(a), 0.0, -np.cos(a)])
        c = p + d * length / 2
        size = (hw, length / 2, 0) if kind == "capsule" else (hw, ht, length / 2)
        out.append(Part(kind, size, (float(c[0]), y, float(c[2])), (0.0, float(-a), 0.0), role))
        p = p + d * length
    return out


def grasper(shaft_r: float) -> tuple[list[Part], list[Part]]:
    """Long, narrow, fenestrated jaws with teeth (a Cadiere or ProGrasp forceps)."""
    jaw = [Part("box", (0.0010, 0.00045, 0.0042), (0, 0.0005, -0.0042)),
           Part("box", (0.00045, 0.0005, 0.0016), (0, 0.0005, -0.0045), role="insert"),
           *_teeth(3, 0.0010, -0.0012, -0.0076, 0.00006)]
    return _body(shaft_r, 0.0032), jaw


def needle_driver(shaft_r: float) -> tuple[list[Part], list[Part]]:
    """Short, wide jaws with serrated carbide inserts (a needle driver)."""
    jaw = [Part("box", (0.0013, 0.0006, 0.0028), (0, 0.00068, -0.0028)),
           Part("box", (0.0011, 0.0001, 0.0025), (0, 0.00005, -0.0029), role="insert"),
           *_teeth(3, 0.0012, -0.0009, -0.0050, 0.00016)]
    return _body(shaft_r, 0.0034), jaw


def scissors(shaft_r: float) -> tuple[list[Part], list[Part]]:
    """Two thin blades curving to one side (curved scissors)."""
    jaw = _chain("box", ((0.005, 0.0, 0.0009, 0.00022), (0.0042, 0.35, 0.0007, 0.00022)), 0.00022)
    return _body(shaft_r, 0.0030), jaw


def maryland(shaft_r: float) -> tuple[list[Part], list[Part]]:
    """Rounded jaws bending along their length (a Maryland dissector)."""
    jaw = [*_chain("capsule", ((0.003, 0.0, 0.0008, 0), (0.0026, 0.45, 0.0007, 0), (0.0022, 0.9, 0.0006, 0)),
                   0.0006),
           *_teeth(2, 0.0006, -0.0012, -0.0034, 0.00002)]
    return _body(shaft_r, 0.0030), jaw


def bipolar(shaft_r: float) -> tuple[list[Part], list[Part]]:
    """Open-frame jaws of two thin rails joined at the tip, insulated wrist (fenestrated bipolar)."""
    jaw = [Part("capsule", (0.00035, 0.0033, 0), (0.0009, 0.0005, -0.0038)),
           Part("capsule", (0.00035, 0.0033, 0), (-0.0009, 0.0005, -0.0038)),
           Part("capsule", (0.00035, 0.0009, 0), (0, 0.0005, -0.0072), ALONG_X)]
    body = _body(shaft_r, 0.0031)
    body.append(Part("cylinder", (0.0033, 0.0015, 0), (0, 0, WRIST_TOP_M - 0.0015), role="insert"))
    return body, jaw


def hook(shaft_r: float) -> tuple[list[Part], list[Part]]:
    """No jaws: an insulated sleeve ending in a thin L-shaped wire (a cautery hook)."""
    body = [Part("cylinder", (shaft_r, (SHAFT_TOP_M - WRIST_TOP_M) / 2, 0), (0, 0, (SHAFT_TOP_M + WRIST_TOP_M) / 2),
                 role="shaft"),
            Part("cylinder", (0.0018, (WRIST_TOP_M + 0.002) / 2, 0), (0, 0, (WRIST_TOP_M - 0.002) / 2), role="insert"),
            Part("capsule", (0.0005, 0.0030, 0), (0, 0, -0.005)),
            Part("capsule", (0.0005, 0.0013, 0), (0.0013, 0, -0.0082), ALONG_X)]
    return body, []


def clip_applier(shaft_r: float) -> tuple[list[Part], list[Part]]:
    """Wide channel-shaped jaws holding a bright clip between them (a clip applier)."""
    jaw = [Part("box", (0.00025, 0.0005, 0.0040), (0.0011, 0.0006, -0.0040)),
           Part("box", (0.00025, 0.0005, 0.0040), (-0.0011, 0.0006, -0.0040)),
           Part("box", (0.0013, 0.00012, 0.0040), (0, 0.0010, -0.0040))]
    body = _body(shaft_r, 0.0036)
    body.append(Part("box", (0.0008, 0.00015, 0.0026), (0, 0, JAW_PIVOT_M - 0.0045), role="insert"))
    return body, jaw


def suction(shaft_r: float) -> tuple[list[Part], list[Part]]:
    """No jaws: a plain tube with side holes and a rim at its open end (suction-irrigation)."""
    r = min(shaft_r, 0.0028)
    body = [Part("cylinder", (shaft_r, (SHAFT_TOP_M - WRIST_TOP_M) / 2, 0), (0, 0, (SHAFT_TOP_M + WRIST_TOP_M) / 2),
                 role="shaft"),
            Part("cylinder", (r, (WRIST_TOP_M + 0.006) / 2, 0), (0, 0, (WRIST_TOP_M - 0.006) / 2)),
            Part("cylinder", (r * 1.05, 0.0003, 0), (0, 0, -0.0060), role="insert"),
            *[Part("sphere", (0.0006, 0, 0), (r * np.cos(a), r * np.sin(a), z), role="insert")
              for a, z in ((0.3, -0.002), (2.4, 0.0), (4.4, 0.002))]]
    return body, []


KINDS = {"grasper": grasper, "needle_driver": needle_driver, "scissors": scissors, "maryland": maryland,
         "bipolar": bipolar, "hook": hook, "clip_applier": clip_applier, "suction": suction}
"""Every instrument kind (``POOLS`` in ``common.sim.random_looks`` splits them)."""

GRASPING = ("grasper", "needle_driver", "maryland", "bipolar", "clip_applier")
"""Kinds whose jaws can hold a needle."""


def kind_parts(kind: str, shaft_r: float) -> tuple[list[Part], list[Part]]:
    """(body parts, one jaw's parts) of ``kind`` with a shaft of radius ``shaft_r`` (m)."""
    body, jaw = KINDS[kind](shaft_r)
    if len(body) > BODY_PARTS or len(jaw) > JAW_PARTS:
        raise AssertionError(f"instrument kind {kind}: more parts than the slots hold")
    return body, jaw

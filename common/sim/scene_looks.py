"""The scene's ``random`` looks: what a ``Look`` holds, the parts of the MJCF model that only a
scene with a look has, and writing a look into the compiled model.

A scene whose ``Appearance.look`` is set compiles a model of its own (``common.sim.scene``'s
``structure_key`` tells them apart): ``LOOK_INSTRUMENTS`` instrument slots of generic primitive
parts (``common.sim.instrument_kinds``) with a material set per slot, ``LOOK_LIGHTS`` lights on
the endoscope of which a look turns on 1 to 4, and textures made from ``TextureLook``s
(``common.sim.look_textures``). Scenes without a look compile the model they always had.
Unused parts go to geom group 3, which the renderer's options leave out.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.geometry.transforms import R_to_quat, rotvec_to_R
from common.sim.instrument_kinds import BODY_PARTS, JAW_PARTS, JAW_PIVOT_M, kind_parts
from common.sim.look_textures import TextureLook, look_texture

LOOK_INSTRUMENTS = 4
LOOK_LIGHTS = 4
TABLE_SIZE = 512
HIDDEN_GROUP = 3  # a geom group MuJoCo's default render options do not draw


@dataclass(frozen=True)
class LightLook:
    """A light on the endoscope: position and direction in the ECM frame (m; the scope looks along
    -z), diffuse colour (RGB, strength included), specular share of it, spot cut-off (deg) and
    exponent."""

    pos: tuple
    dir: tuple
    rgb: tuple
    specular: float = 0.9
    cutoff: float = 70.0
    exponent: float = 2.0


@dataclass(frozen=True)
class InstrumentLook:
    """An instrument slot's kind (``common.sim.instrument_kinds.KINDS``), shaft radius (m) and the
    finishes of its shaft, jaws and inserts, each (r, g, b, specular, shininess, reflectance)."""

    kind: str
    shaft_radius_m: float
    shaft: tuple
    jaw: tuple
    insert: tuple


@dataclass(frozen=True)
class Look:
    """Everything a ``random`` look adds to an ``Appearance``: the pad's and the background's
    textures (their colours are the texture's: the materials are white), the lights (1 to
    ``LOOK_LIGHTS``; they replace the scope light and fill) and one ``InstrumentLook`` per slot."""

    tissue: TextureLook
    table: TextureLook
    lights: tuple
    instruments: tuple


# ---------------------------------------------------------------- MJCF of a scene with a look

def _geom(name: str, material: str) -> str:
    return (f'<geom name="{name}" type="box" size="0.001 0.001 0.001" material="{material}" '
            f'group="{HIDDEN_GROUP}"/>')


def instruments_mjcf(hidden_pos: str) -> str:
    """The instrument slots' bodies: generic parts that ``apply_look`` shapes per scene."""
    out = []
    for i in range(LOOK_INSTRUMENTS):
        body = "".join(_geom(f"instrument{i}_part{k}", f"jaw{i}") for k in range(BODY_PARTS))
        jaws = "".join(
            f'<body name="instrument{i}_jawbody{j}" pos="0 0 {JAW_PIVOT_M}">'
            + "".join(_geom(f"instrument{i}_jaw{j}_part{k}", f"jaw{i}") for k in range(JAW_PARTS)) + "</body>"
            for j in range(2))
        out.append(f'\n    <body name="instrument{i}" mocap="true" pos="{hidden_pos}">{body}{jaws}</body>')
    return "".join(out)


def materials_mjcf() -> str:
    return "".join(f'<material name="{r}{i}"/>' for i in range(LOOK_INSTRUMENTS) for r in ("shaft", "jaw", "insert"))


def lights_mjcf() -> str:
    """The lights beyond the scope light and fill (``scope_light``, ``scope_fill``)."""
    return "".join(f'\n      <light name="look_light{k}" pos="0 0 0" dir="0 0 -1" castshadow="false" cutoff="70" '
                   f'exponent="2"/>' for k in range(2, LOOK_LIGHTS))


# ---------------------------------------------------------------- writing a look into the model

_GEOM_TYPES = {"box": "mjGEOM_BOX", "cylinder": "mjGEOM_CYLINDER", "capsule": "mjGEOM_CAPSULE",
               "sphere": "mjGEOM_SPHERE", "ellipsoid": "mjGEOM_ELLIPSOID"}


class LookWriter:
    """Writes looks into a compiled model with the slots above (ids looked up once)."""

    def __init__(self, mujoco, model):
        self._mj = mujoco
        m = self.model = model
        idof = lambda kind, name: mujoco.mj_name2id(m, kind, name)  # noqa: E731
        G, MAT, L = mujoco.mjtObj.mjOBJ_GEOM, mujoco.mjtObj.mjOBJ_MATERIAL, mujoco.mjtObj.mjOBJ_LIGHT
        self.body_geoms = [[idof(G, f"instrument{i}_part{k}") for k in range(BODY_PARTS)]
                           for i in range(LOOK_INSTRUMENTS)]
        self.jaw_geoms = [[[idof(G, f"instrument{i}_jaw{j}_part{k}") for k in range(JAW_PARTS)] for j in range(2)]
                          for i in range(LOOK_INSTRUMENTS)]
        self.materials = [{r: idof(MAT, f"{r}{i}") for r in ("shaft", "jaw", "insert")}
                          for i in range(LOOK_INSTRUMENTS)]
        self.light_ids = [idof(L, "scope_light"), idof(L, "scope_fill")] + [idof(L, f"look_light{k}")
                                                                         for k in range(2, LOOK_LIGHTS)]
        self._types = {k: int(getattr(mujoco.mjtGeom, v)) for k, v in _GEOM_TYPES.items()}
        self._kinds = [None] * LOOK_INSTRUMENTS

    def _part(self, g: int, part, slot: int) -> None:
        m = self.model
        m.geom_type[g] = self._types[part.kind]
        size = np.zeros(3)
        size[:len(part.size)] = part.size
        m.geom_size[g] = size
        m.geom_pos[g] = part.pos
        m.geom_quat[g] = R_to_quat(rotvec_to_R(part.rot))
        m.geom_matid[g] = self.materials[slot][part.role]
        m.geom_group[g] = 0
        m.geom_sameframe[g] = 0                # the compiler found pos 0 and no rotation: not any more
        m.geom_rbound[g] = float(np.linalg.norm(size))

    def _hide(self, g: int) -> None:
        self.model.geom_group[g] = HIDDEN_GROUP

    def instruments(self, looks) -> None:
        """Shape and finish every slot."""
        m = self.model
        for i, il in enumerate(looks[:LOOK_INSTRUMENTS]):
            for role in ("shaft", "jaw", "insert"):
                r, g, b, spec, shin, refl = getattr(il, role)
                k = self.materials[i][role]
                m.mat_rgba[k] = [r, g, b, 1.0]
                m.mat_specular[k], m.mat_shininess[k], m.mat_reflectance[k] = spec, shin, refl
            key = (il.kind, il.shaft_radius_m)
            if self._kinds[i] == key:
                continue
            self._kinds[i] = key
            body, jaw = kind_parts(il.kind, il.shaft_radius_m)
            for k, g in enumerate(self.body_geoms[i]):
                self._part(g, body[k], i) if k < len(body) else self._hide(g)
            for j in range(2):
                for k, g in enumerate(self.jaw_geoms[i][j]):
                    if k < len(jaw):
                        self._part(g, jaw[k] if j == 0 else jaw[k].mirrored(), i)
                    else:
                        self._hide(g)

    def lights(self, looks, shadows: bool) -> None:
        """Turn on one light per ``LightLook`` (the first may cast shadows), the rest off."""
        m = self.model
        for k, lid in enumerate(self.light_ids):
            on = k < len(looks)
            m.light_active[lid] = on
            if not on:
                continue
            lk = looks[k]
            d = np.asarray(lk.dir, float)
            m.light_pos[lid] = m.light_pos0[lid] = lk.pos
            m.light_dir[lid] = m.light_dir0[lid] = d / np.linalg.norm(d)
            m.light_diffuse[lid] = lk.rgb
            m.light_specular[lid] = np.asarray(lk.rgb) * lk.specular
            m.light_cutoff[lid], m.light_exponent[lid] = lk.cutoff, lk.exponent
            m.light_castshadow[lid] = bool(shadows) and k == 0


def look_textures(look: Look, size: int) -> tuple[np.ndarray, np.ndarray]:
    """The (tissue, table) textures of a look, RGB uint8 (size x size, TABLE_SIZE x TABLE_SIZE)."""
    quarter = look_texture(look.table, TABLE_SIZE // 2)       # mirrored into a tile without seams
    half = np.hstack([quarter, quarter[:, ::-1]])
    return look_texture(look.tissue, size), np.ascontiguousarray(np.vstack([half, half[::-1]]))

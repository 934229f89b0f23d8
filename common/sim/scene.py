"""The built-in suturing scene: an MJCF model with procedurally generated meshes and textures.

World frame: the table top at z = 0, z up; a tissue phantom pad centred on the origin. The
needle, the endoscope (ECM) and the two instruments are mocap bodies, so their poses are set
per frame without simulating dynamics. The ECM body carries the left/right cameras and the
endoscope's lights. A MuJoCo camera looks along its -z with y up; the OpenCV camera frame
(x right, y down, z forward) is that frame rotated by pi about x. Since the built-in rig has
``T_ecm_cam = diag(1, -1, -1)`` (plus the baseline offset), the MuJoCo cameras are simply the
ECM frame shifted along x. All lengths in metres.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from common.geometry.camera import StereoRig
from common.geometry.needle import NeedleModel
from common.geometry.transforms import R_to_quat, make_T
from common.sim.scene_meshes import (
    PHANTOM_SIZE,
    PHANTOM_TOP,
    needle_mesh,
    perpendicular,
    phantom_mesh,
    sweep_tube,
    thread_path,
)
from common.sim.scene_looks import (
    LOOK_INSTRUMENTS,
    TABLE_SIZE,
    Look,
    LookWriter,
    instruments_mjcf,
    lights_mjcf,
    look_textures,
    materials_mjcf,
)
from common.sim.scene_textures import TEXTURE_VARIANTS, cached_texture


# ---------------------------------------------------------------- scene description

@dataclass
class Appearance:
    """Everything about how the scene looks (colours 0..1, lengths in m)."""

    tissue_rgb: tuple = (0.86, 0.52, 0.50)
    tissue_specular: float = 0.35
    tissue_shininess: float = 0.25
    table_rgb: tuple = (0.12, 0.16, 0.14)
    needle_rgb: tuple = (0.78, 0.78, 0.80)
    needle_specular: float = 0.9
    needle_shininess: float = 0.85
    needle_reflectance: float = 0.0
    wire_diameter_m: float = 0.0008
    tip_length_m: float = 0.0018
    tip_exponent: float = 0.75
    swage_scale: float = 1.08
    thread_rgb: tuple = (0.35, 0.15, 0.55)
    thread_diameter_m: float = 0.00035
    thread_length_m: float = 0.06
    thread_visible: bool = True  # False: no thread drawn (the threadless looks)
    light_diffuse: float = 0.75
    light_rgb: tuple = (1.0, 0.97, 0.92)
    light_offset: tuple = (0.0, 0.004, 0.0)  # position of the scope's light in the ECM frame
    ambient: float = 0.12
    shadows: bool = False  # cast shadows: about 3x the rendering time on the CPU
    texture_seed: int = 0
    look: Look | None = None  # a ``random`` look (common.sim.scene_looks): textures, lights, instrument kinds


JAW_PIVOT_M = 0.0045
"""Distance of the jaws' pivot from the instrument body's origin (m), along the shaft."""

T_BODY_JAW = np.array([[0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, JAW_PIVOT_M], [0, 0, 0, 1.0]])
"""The jaw frame of ``docs/dataset.md`` in the instrument body (whose z runs up the shaft and whose
x the jaws turn about): origin at the pivot, z along the closed jaws towards their tips, y the
axis they open about, x = y cross z."""


@dataclass
class Instrument:
    """A patient-side instrument: the body's origin near the jaw tips (world), shaft direction from
    there towards the trocar (world unit vector), roll about the shaft (rad) and jaw opening (rad,
    0 closed). ``T_world_jaw`` is its jaw frame (``T_BODY_JAW``); ``from_jaw`` the inverse."""

    tip: tuple
    shaft_dir: tuple
    roll: float = 0.0
    jaw_open: float = 0.3

    @property
    def T_world_body(self) -> np.ndarray:
        return make_T(_frame_from_z(np.asarray(self.shaft_dir, float), self.roll), self.tip)

    @property
    def T_world_jaw(self) -> np.ndarray:
        return self.T_world_body @ T_BODY_JAW

    @classmethod
    def from_jaw(cls, T_world_jaw: np.ndarray, jaw_rad: float) -> "Instrument":
        """The instrument whose jaw frame is ``T_world_jaw`` (4x4, world), opened ``jaw_rad``."""
        T_wb = np.asarray(T_world_jaw, float) @ np.linalg.inv(T_BODY_JAW)
        z = T_wb[:3, 2]
        x0 = perpendicular(z)
        y0 = np.cross(z, x0)
        x = T_wb[:3, 0]
        return cls(tuple(T_wb[:3, 3]), tuple(z), float(np.arctan2(x @ y0, x @ x0)), float(jaw_rad))


@dataclass
class SceneSpec:
    """A complete scene: rig, needle model, needle pose, appearance, up to two instruments."""

    rig: StereoRig = field(default_factory=StereoRig.default)
    needle: NeedleModel = field(default_factory=NeedleModel)
    T_world_needle: np.ndarray = field(default_factory=lambda: make_T(np.eye(3), [0, 0, 0.02]))
    appearance: Appearance = field(default_factory=Appearance)
    instruments: list = field(default_factory=list)
    thread_seed: int = 0
    markers: list = field(default_factory=list)  # (x, y, z, radius) world spheres, for calibration tests
    texture_size: int = 1024
    msaa: int = 4  # multisample anti-aliasing (0 = off: ~2.5x faster on the CPU, jagged thin wires)


MAX_INSTRUMENTS = 2
THREAD_POINTS = 240
_HIDDEN = np.array([0.0, 0.0, -5.0])  # where unused instruments wait, out of sight under the table


def _fmt(a) -> str:
    return " ".join(f"{v:.9g}" for v in np.asarray(a, dtype=float).reshape(-1))


def _frame_from_z(z: np.ndarray, roll: float = 0.0) -> np.ndarray:
    """Rotation of a frame whose z axis is ``z`` (unit), rolled about it."""
    z = np.asarray(z, dtype=float)
    z = z / np.linalg.norm(z)
    x = perpendicular(z)
    y = np.cross(z, x)
    c, s = np.cos(roll), np.sin(roll)
    x, y = c * x + s * y, -s * x + c * y
    return np.stack([x, y, z], axis=1)


def _quat_from_z(z: np.ndarray, roll: float = 0.0) -> np.ndarray:
    """Quaternion [w,x,y,z] of a frame whose z axis is ``z`` (unit), rolled about it."""
    return R_to_quat(_frame_from_z(z, roll))


def rig_check(rig: StereoRig) -> None:
    """The MuJoCo cameras render an ideal centred pinhole along -z: refuse rigs they cannot render."""
    for cam in rig.cameras:
        K = cam.K
        w, h = cam.width, cam.height
        if (abs(K[0, 0] - K[1, 1]) > 1e-9 * K[0, 0] or abs(K[0, 2] - (w - 1) / 2) > 1e-9
                or abs(K[1, 2] - (h - 1) / 2) > 1e-9 or K[0, 1] != 0 or np.any(cam.dist)):
            raise ValueError(f"sim: camera {cam.name} must be an undistorted centred pinhole with "
                             f"square pixels (got K={K.tolist()})")
        R = cam.T_ecm_cam[:3, :3]
        if not np.allclose(R, np.diag([1.0, -1.0, -1.0]), atol=1e-9):
            raise ValueError(f"sim: camera {cam.name} must look along -z_ecm (T_ecm_cam rotation "
                             f"diag(1,-1,-1)), got {R.tolist()}")


def _mesh_xml(name: str, v, n, f, uv=None) -> str:
    tex = f' texcoord="{_fmt(uv)}"' if uv is not None else ""
    return (f'<mesh name="{name}" inertia="shell" vertex="{_fmt(v)}" normal="{_fmt(n)}"{tex} '
            f'face="{" ".join(map(str, np.asarray(f).reshape(-1)))}"/>')


def structure_key(spec: SceneSpec) -> tuple:
    """What fixes the compiled model; scenes with the same key share it (see SceneModel.apply)."""
    rig = spec.rig
    return (rig.left.width, rig.left.height, float(rig.left.K[1, 1]),
            tuple(rig.left.T_ecm_cam[:3, 3]), tuple(rig.right.T_ecm_cam[:3, 3]),
            len(spec.markers), spec.texture_size, spec.needle, int(spec.msaa), spec.appearance.look is not None)


def build_mjcf(spec: SceneSpec) -> str:
    """MJCF of the scene's structure. Everything that varies between scenes (poses, meshes of the
    needle and thread, colours, textures, lights) is written into the compiled model by
    ``SceneModel.apply``; the values here are placeholders."""
    rig = spec.rig
    rig_check(rig)
    w, h = rig.left.width, rig.left.height
    fovy_deg = np.rad2deg(2 * np.arctan((h / 2) / rig.left.K[1, 1]))
    nv, nn, nf = needle_mesh(spec.needle, spec.needle.wire_diameter_m)
    line = np.stack([np.linspace(0, 0.05, THREAD_POINTS), np.zeros(THREAD_POINTS), np.zeros(THREAD_POINTS)], 1)
    tv, tn, tf = sweep_tube(line, np.full(THREAD_POINTS, 0.0002), 8)
    pv, puv, pf = phantom_mesh()
    sx, sy = PHANTOM_SIZE
    ts = spec.texture_size
    look = spec.appearance.look is not None
    inst = []
    for i in range(0 if look else MAX_INSTRUMENTS):
        inst.append(f"""
    <body name="instrument{i}" mocap="true" pos="{_fmt(_HIDDEN)}">
      <geom name="instrument{i}_shaft" type="cylinder" fromto="0 0 0.011 0 0 0.25" size="0.0042" material="shaft"/>
      <geom name="instrument{i}_wrist" type="cylinder" fromto="0 0 {JAW_PIVOT_M} 0 0 0.011" size="0.0032" material="jaw"/>
      <geom name="instrument{i}_pin" type="cylinder" fromto="-0.0028 0 {JAW_PIVOT_M} 0.0028 0 {JAW_PIVOT_M}" size="0.0012" material="jaw"/>
      <body name="instrument{i}_jawbody0" pos="0 0 {JAW_PIVOT_M}"><geom name="instrument{i}_jaw0" type="box" pos="0 0.0006 -0.0035" size="0.0011 0.0005 0.0036" material="jaw"/></body>
      <body name="instrument{i}_jawbody1" pos="0 0 {JAW_PIVOT_M}"><geom name="instrument{i}_jaw1" type="box" pos="0 -0.0006 -0.0035" size="0.0011 0.0005 0.0036" material="jaw"/></body>
    </body>""")
    markers = [f"""
    <geom name="marker{i}" type="sphere" pos="0 0 -5" size="0.001" rgba="0.1 0.9 0.2 1"/>"""
               for i in range(len(spec.markers))]
    if look:
        inst = [instruments_mjcf(_fmt(_HIDDEN))]
    cams = "\n".join(f'      <camera name="{c.name}" pos="{_fmt(c.T_ecm_cam[:3, 3])}" fovy="{fovy_deg:.12g}"/>'
                     for c in rig.cameras)
    return f"""<mujoco model="needletrack_suturing">
  <compiler angle="radian" inertiafromgeom="false"/>
  <statistic extent="1" center="0 0 0.05"/>
  <visual>
    <global offwidth="{w}" offheight="{h}"/>
    <map znear="0.002" zfar="3"/>
    <quality shadowsize="2048" offsamples="{int(spec.msaa)}"/>
    <headlight ambient="0.1 0.1 0.1" diffuse="0 0 0" specular="0 0 0"/>
  </visual>
  <asset>
    <texture name="tissue" type="2d" builtin="flat" rgb1="1 1 1" width="{ts}" height="{ts}"/>
    <texture name="table" type="2d" builtin="flat" rgb1="1 1 1" width="{TABLE_SIZE if look else 256}" height="{TABLE_SIZE if look else 256}"/>
    <material name="tissue" texture="tissue"/>
    <material name="tissue_side"/>
    <material name="table" texture="table" texrepeat="{'3 3' if look else '4 4'}" specular="0.05"/>
    <material name="needle"/>
    <material name="thread"/>
    <material name="shaft" rgba="0.08 0.08 0.09 1" specular="0.5" shininess="0.6"/>
    <material name="jaw" rgba="0.62 0.63 0.66 1" specular="0.8" shininess="0.8"/>{materials_mjcf() if look else ''}
    {_mesh_xml("needle", nv, nn, nf)}
    {_mesh_xml("thread", tv, tn, tf)}
    {_mesh_xml("phantom", pv, np.tile([0.0, 0.0, 1.0], (len(pv), 1)), pf, puv)}
  </asset>
  <worldbody>
    <geom name="table" type="box" size="0.4 0.3 0.002" pos="0 0 -0.002" material="table"/>
    <geom name="phantom_body" type="box" size="{sx / 2 - 0.003:.6f} {sy / 2 - 0.003:.6f} {PHANTOM_TOP / 2 - 0.001:.6f}" pos="0 0 {PHANTOM_TOP / 2 - 0.001:.6f}" material="tissue_side"/>
    <geom name="phantom" type="mesh" mesh="phantom" material="tissue"/>
    <geom name="thread" type="mesh" mesh="thread" material="thread"/>
    <body name="needle" mocap="true">
      <geom name="needle" type="mesh" mesh="needle" material="needle"/>
    </body>
    <body name="ecm" mocap="true" pos="0 0 0.3">
{cams}
      <light name="scope_light" pos="0 0.004 0" dir="0 0 -1" castshadow="true" cutoff="70" exponent="2"/>
      <light name="scope_fill" pos="0 -0.004 0" dir="0 0 -1" specular="0 0 0" castshadow="false" cutoff="80" exponent="1"/>{lights_mjcf() if look else ''}
    </body>{''.join(inst)}{''.join(markers)}
  </worldbody>
</mujoco>
"""


class SceneModel:
    """A compiled scene whose varying parts are rewritten in place by ``apply(spec)``, so one model
    (and one render context) serves every scene with the same ``structure_key``."""

    def __init__(self, spec: SceneSpec):
        import mujoco
        self._mj = mujoco
        self.key = structure_key(spec)
        self.model = mujoco.MjModel.from_xml_string(build_mjcf(spec))
        m = self.model
        ids = lambda kind, name: mujoco.mj_name2id(m, kind, name)  # noqa: E731
        G, B, M, T, MAT, L = (mujoco.mjtObj.mjOBJ_GEOM, mujoco.mjtObj.mjOBJ_BODY, mujoco.mjtObj.mjOBJ_MESH,
                              mujoco.mjtObj.mjOBJ_TEXTURE, mujoco.mjtObj.mjOBJ_MATERIAL, mujoco.mjtObj.mjOBJ_LIGHT)
        self.mesh = {n: ids(M, n) for n in ("needle", "thread", "phantom")}
        self.tex = {n: ids(T, n) for n in ("tissue", "table")}
        self.mat = {n: ids(MAT, n) for n in ("tissue", "tissue_side", "table", "needle", "thread")}
        self.light = {n: ids(L, n) for n in ("scope_light", "scope_fill")}
        looks = spec.appearance.look is not None
        self.n_instruments = LOOK_INSTRUMENTS if looks else MAX_INSTRUMENTS
        self.looks = LookWriter(mujoco, m) if looks else None
        self.mocap = {n: int(m.body_mocapid[ids(B, n)]) for n in
                      ["needle", "ecm"] + [f"instrument{i}" for i in range(self.n_instruments)]}
        self.jaws = [(ids(B, f"instrument{i}_jawbody0"), ids(B, f"instrument{i}_jawbody1"))
                     for i in range(self.n_instruments)]
        self.markers = [ids(G, f"marker{i}") for i in range(len(spec.markers))]
        # needle and thread vertices are written in their body frames: undo the compiler's
        # re-centring of those meshes
        for name in ("needle", "thread"):
            g = ids(G, name)
            m.geom_pos[g] = 0.0
            m.geom_quat[g] = [1.0, 0.0, 0.0, 0.0]
            m.geom_rbound[g] = 1.0
            m.geom_aabb[g] = [0, 0, 0, 1, 1, 1]
        self._tex_state = {}
        self._mesh_state = {}

    def _write_mesh(self, name: str, verts, normals, state) -> bool:
        if self._mesh_state.get(name) == state:
            return False
        m, k = self.model, self.mesh[name]
        va, vn = m.mesh_vertadr[k], m.mesh_vertnum[k]
        na, nn = m.mesh_normaladr[k], m.mesh_normalnum[k]
        if len(verts) != vn or len(normals) != nn:
            raise AssertionError(f"mesh {name}: {len(verts)} vertices for {vn} slots")
        m.mesh_vert[va:va + vn] = verts
        m.mesh_normal[na:na + nn] = normals
        self._mesh_state[name] = state
        return True

    def _write_texture(self, name: str, rgb: np.ndarray, state) -> bool:
        if self._tex_state.get(name) == state:
            return False
        m, k = self.model, self.tex[name]
        adr, n = m.tex_adr[k], m.tex_width[k] * m.tex_height[k] * m.tex_nchannel[k]
        m.tex_data[adr:adr + n] = rgb.reshape(-1)
        self._tex_state[name] = state
        return True

    def _write_look_textures(self, look: Look, size: int) -> list:
        """The pad's and background's textures of a look (made only when the look's change)."""
        if self._tex_state.get("tissue") == look.tissue and self._tex_state.get("table") == look.table:
            return []
        tissue, table = look_textures(look, size)
        self._write_texture("tissue", tissue, look.tissue)
        self._write_texture("table", table, look.table)
        self._side_rgb = tissue[::16, ::16].reshape(-1, 3).mean(axis=0) / 255.0 * 0.7
        return [self.tex["tissue"], self.tex["table"]]

    def apply(self, spec: SceneSpec) -> tuple[list, list]:
        """Write the scene's varying parts; returns (mesh ids, texture ids) to re-upload."""
        if structure_key(spec) != self.key:
            raise ValueError("scene: structure differs from the compiled model")
        m, ap = self.model, spec.appearance
        meshes, textures = [], []
        shape = (ap.wire_diameter_m, ap.tip_length_m, ap.tip_exponent, ap.swage_scale)
        if self._write_mesh("needle", *needle_mesh(spec.needle, ap.wire_diameter_m, ap.tip_length_m,
                                                   tip_exponent=ap.tip_exponent,
                                                   swage_scale=ap.swage_scale)[:2], state=shape):
            meshes.append(self.mesh["needle"])
        tstate = (spec.thread_seed, ap.thread_length_m, ap.thread_diameter_m, spec.T_world_needle.tobytes())
        if self._mesh_state.get("thread") != tstate:
            path = thread_path(spec.T_world_needle, spec.needle, np.random.default_rng(spec.thread_seed),
                               ap.thread_length_m, ap.thread_diameter_m / 2, THREAD_POINTS)
            tv, tn, _ = sweep_tube(path, np.full(len(path), ap.thread_diameter_m / 2), 8)
            self._write_mesh("thread", tv, tn, tstate)
            meshes.append(self.mesh["thread"])
        if ap.look is not None:
            textures += self._write_look_textures(ap.look, spec.texture_size)
        else:
            if self._write_texture("tissue", cached_texture("tissue", ap.texture_seed, spec.texture_size),
                                   ("tissue", ap.texture_seed % TEXTURE_VARIANTS)):
                textures.append(self.tex["tissue"])
            if self._write_texture("table", cached_texture("table", ap.texture_seed + 7, 256),
                                   ("table", (ap.texture_seed + 7) % TEXTURE_VARIANTS)):
                textures.append(self.tex["table"])
        mat = self.mat
        m.mat_rgba[mat["tissue"]] = [*ap.tissue_rgb, 1]
        m.mat_specular[mat["tissue"]] = ap.tissue_specular
        m.mat_shininess[mat["tissue"]] = ap.tissue_shininess
        m.mat_rgba[mat["tissue_side"]] = [*(np.asarray(ap.tissue_rgb) * 0.7), 1]
        m.mat_specular[mat["tissue_side"]] = 0.2
        m.mat_rgba[mat["table"]] = [*ap.table_rgb, 1]
        m.mat_rgba[mat["needle"]] = [*ap.needle_rgb, 1]
        m.mat_specular[mat["needle"]] = ap.needle_specular
        m.mat_shininess[mat["needle"]] = ap.needle_shininess
        m.mat_reflectance[mat["needle"]] = ap.needle_reflectance
        m.mat_rgba[mat["thread"]] = [*ap.thread_rgb, 1.0 if ap.thread_visible else 0.0]
        m.mat_specular[mat["thread"]] = 0.15
        m.mat_shininess[mat["thread"]] = 0.2
        rgb = np.asarray(ap.light_rgb) * ap.light_diffuse
        lo = np.asarray(ap.light_offset, dtype=float)
        key, fill = self.light["scope_light"], self.light["scope_fill"]
        m.light_pos[key], m.light_pos0[key] = lo, lo
        m.light_diffuse[key], m.light_specular[key] = rgb, rgb * 0.9
        m.light_castshadow[key] = bool(ap.shadows)
        m.light_pos[fill], m.light_pos0[fill] = -lo, -lo
        m.light_diffuse[fill] = rgb * 0.35
        m.vis.headlight.ambient[:] = ap.ambient
        if ap.look is not None:
            m.mat_rgba[mat["tissue_side"]] = [*self._side_rgb, 1]
            self.looks.lights(ap.look.lights, ap.shadows)
            self.looks.instruments(ap.look.instruments)
        for i, (j0, j1) in enumerate(self.jaws):
            ja = spec.instruments[i].jaw_open / 2 if i < len(spec.instruments) else 0.3
            m.body_quat[j0] = [np.cos(ja / 2), np.sin(ja / 2), 0, 0]
            m.body_quat[j1] = [np.cos(-ja / 2), np.sin(-ja / 2), 0, 0]
        for g, mk in zip(self.markers, spec.markers):
            m.geom_pos[g] = mk[:3]
            m.geom_size[g][0] = mk[3]
            m.geom_rbound[g] = mk[3]
        return meshes, textures

    def set_poses(self, data, spec: SceneSpec) -> None:
        """Mocap poses of the needle and the instruments (the ECM is set per frame)."""
        self.set_mocap(data, "needle", spec.T_world_needle)
        for i in range(self.n_instruments):
            name = f"instrument{i}"
            if i < len(spec.instruments):
                ins = spec.instruments[i]
                data.mocap_pos[self.mocap[name]] = ins.tip
                data.mocap_quat[self.mocap[name]] = _quat_from_z(np.asarray(ins.shaft_dir, float), ins.roll)
            else:
                data.mocap_pos[self.mocap[name]] = _HIDDEN
                data.mocap_quat[self.mocap[name]] = [1, 0, 0, 0]

    def set_mocap(self, data, body: str, T: np.ndarray) -> None:
        i = self.mocap[body]
        data.mocap_pos[i] = T[:3, 3]
        data.mocap_quat[i] = R_to_quat(T[:3, :3])

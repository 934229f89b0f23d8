"""An arm's kinematic error: instruments reported as a dVRK reports them (docs/datasets.md).

A real patient-side arm reports its jaw frame (``measured_cp``, mapped into world by the arm's
registration) and its opening (``jaw/measured_js``) with an error that the true motion does not
show. ``ArmError`` is one arm's error over one take, drawn once from its ``ArmErrorConfig`` and a
seed, deterministic frame by frame:

- a registration error of the arm's base: a rigid transform ``T_reg`` (world), fixed per arm and
  take, whose rotation is ``registration_deg`` about the tool's first position and whose
  translation there is ``registration_mm``, each drawn in [1/2, 1] of the setting in a random
  direction; as the tool moves from that point, the position error it makes changes by
  ``(R_reg - I) dp`` (the lever of a registration's rotation);
- a part that changes slowly with the arm's configuration (joint offsets, cable stretch): a smooth,
  bounded function of the true jaw pose (its position over ``drift_length_m``, its orientation
  over ``drift_turn_deg``), at most ``drift_mm`` and ``drift_deg``, in the jaw frame; constant
  while the arm keeps still, it drifts as the arm moves;
- a jaw-angle offset, fixed per arm and take, uniform in +-``jaw_offset_deg``;
- per-frame noise: ``noise_mm`` and ``noise_deg`` (1 sigma per axis, in the jaw frame) and
  ``jaw_noise_deg``.

``T_world_jaw_reported = T_reg @ T_world_jaw @ E_cfg(T_world_jaw) @ E_noise``;
``jaw_rad_reported = clip(jaw_rad + offset + noise, 0, pi)``.

Presets (``ARM_ERRORS``): ``exact`` (the report is the truth) and ``dvrk`` (a few mm and degrees,
the magnitudes of docs/datasets.md). A spec string names a preset and optional overrides,
``dvrk:registration_mm=5,noise_mm=0.2`` (``arm_error_config``). Lengths in the config are mm and
degrees for the reader; the poses are metres and radians.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace
from typing import Optional

import numpy as np

from common.data.instruments import InstrumentPose
from common.geometry.transforms import make_T, rotvec_to_R

N_FEATURES = 8                      # random Fourier features of the configuration-dependent part
DRAW_LOW = 0.5                      # registration magnitudes are drawn in [DRAW_LOW, 1] of the setting


@dataclass(frozen=True)
class ArmErrorConfig:
    """How large an arm's reported error is (see the module docstring); all zero: exact."""

    registration_mm: float = 0.0    # base registration: translation at the tool's first position
    registration_deg: float = 0.0   # base registration: rotation
    drift_mm: float = 0.0           # configuration-dependent part: at most this translation
    drift_deg: float = 0.0          # ... and this rotation
    drift_length_m: float = 0.03    # tool travel over which that part changes by about its size
    drift_turn_deg: float = 30.0    # tool turn over which it does
    jaw_offset_deg: float = 0.0     # jaw-angle offset: uniform in +- this
    noise_mm: float = 0.0           # per-frame noise, 1 sigma per axis
    noise_deg: float = 0.0
    jaw_noise_deg: float = 0.0

    def __post_init__(self):
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or v < 0:
                raise ValueError(f"arm error: {f.name} must be a finite number >= 0, got {v!r}")
        if self.drift_length_m <= 0 or self.drift_turn_deg <= 0:
            raise ValueError("arm error: drift_length_m and drift_turn_deg must be > 0")

    @property
    def exact(self) -> bool:
        """True when the report is the truth (every error magnitude zero)."""
        return all(getattr(self, k) == 0 for k in ERROR_FIELDS)

    def spec(self) -> str:
        """The canonical spec string: the preset it equals, else ``exact:`` and its nonzero overrides."""
        for name, preset in ARM_ERRORS.items():
            if preset == self:
                return name
        base = ARM_ERRORS["exact"]
        diff = {k: v for k, v in asdict(self).items() if v != getattr(base, k)}
        return "exact:" + ",".join(f"{k}={v:g}" for k, v in sorted(diff.items()))


ERROR_FIELDS = ("registration_mm", "registration_deg", "drift_mm", "drift_deg", "jaw_offset_deg", "noise_mm",
                "noise_deg", "jaw_noise_deg")

ARM_ERRORS = {
    "exact": ArmErrorConfig(),
    # 2-5 mm / 2-4 deg at the tool in all: docs/datasets.md, "Instruments as a dVRK reports them"
    "dvrk": ArmErrorConfig(registration_mm=4.5, registration_deg=3.5, drift_mm=1.5, drift_deg=1.5,
                           drift_length_m=0.015, drift_turn_deg=45.0, jaw_offset_deg=5.0, noise_mm=0.1,
                           noise_deg=0.1, jaw_noise_deg=0.5),
}


def arm_error_config(spec: "str | ArmErrorConfig | None") -> ArmErrorConfig:
    """The config of a spec string: a preset name (``exact``, ``dvrk``), optionally followed by
    ``:`` and ``field=value`` overrides separated by commas; None is ``exact``."""
    if spec is None:
        return ARM_ERRORS["exact"]
    if isinstance(spec, ArmErrorConfig):
        return spec
    name, _, rest = str(spec).strip().partition(":")
    if name not in ARM_ERRORS:
        raise ValueError(f"arm error: unknown preset {name!r}; one of {sorted(ARM_ERRORS)}, "
                         "optionally followed by ':field=value,...'")
    cfg = ARM_ERRORS[name]
    known = {f.name for f in fields(ArmErrorConfig)}
    over = {}
    for item in filter(None, (s.strip() for s in rest.split(","))):
        key, eq, value = item.partition("=")
        key = key.strip()
        if not eq or key not in known:
            raise ValueError(f"arm error: {item!r} in {spec!r} is not field=value with a field of {sorted(known)}")
        try:
            over[key] = float(value)
        except ValueError:
            raise ValueError(f"arm error: {key}: not a number: {value!r}") from None
    return replace(cfg, **over)


def _unit(rng, n: int) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _saturate(v: np.ndarray, amplitude: float) -> np.ndarray:
    """``v`` scaled smoothly into a ball of radius ``amplitude`` (``amplitude * v / sqrt(1 + |v|^2)``)."""
    return amplitude * v / np.sqrt(1.0 + v @ v)


@dataclass
class ArmError:
    """One arm's error over one take (``draw`` makes one; the module docstring says what it is)."""

    config: ArmErrorConfig
    key: tuple                      # seeds the per-frame noise, with the frame's step
    T_reg: np.ndarray               # registration error (world, 4x4)
    jaw_offset_rad: float
    origin: np.ndarray              # the tool's first position (world, m): where the features start
    w: np.ndarray                   # (2, K, 12) feature directions (translation part, rotation part)
    phase: np.ndarray               # (2, K)
    u: np.ndarray                   # (2, K, 3) feature outputs

    @classmethod
    def draw(cls, config: ArmErrorConfig, key, T_world_jaw0: np.ndarray) -> "ArmError":
        """The error of the arm whose jaws start at ``T_world_jaw0`` (4x4, world), drawn from
        ``key`` (a sequence of ints: the run's seed, the take, the arm)."""
        key = tuple(int(k) for k in key)
        rng = np.random.default_rng(key)
        origin = np.asarray(T_world_jaw0, float)[:3, 3].copy()
        t = _unit(rng, 1)[0] * rng.uniform(DRAW_LOW, 1.0) * config.registration_mm * 1e-3
        R = rotvec_to_R(_unit(rng, 1)[0] * rng.uniform(DRAW_LOW, 1.0) * np.deg2rad(config.registration_deg))
        T_reg = make_T(R, origin + t - R @ origin)          # turns about the tool's first position
        jaw = float(rng.uniform(-1.0, 1.0) * np.deg2rad(config.jaw_offset_deg))
        w = rng.normal(size=(2, N_FEATURES, 12))
        phase = rng.uniform(0.0, 2 * np.pi, size=(2, N_FEATURES))
        u = np.stack([_unit(rng, N_FEATURES), _unit(rng, N_FEATURES)])
        return cls(config, key, T_reg, jaw, origin, w, phase, u)

    def configuration_error(self, T_world_jaw: np.ndarray) -> np.ndarray:
        """``E_cfg``: the configuration-dependent part at the true jaw pose (4x4, jaw frame)."""
        c = self.config
        if c.drift_mm == 0 and c.drift_deg == 0:
            return np.eye(4)
        T = np.asarray(T_world_jaw, float)
        x = np.concatenate([(T[:3, 3] - self.origin) / c.drift_length_m,
                            T[:3, :3].reshape(-1) / np.deg2rad(c.drift_turn_deg)])
        v = np.sqrt(2.0 / N_FEATURES) * np.einsum("pk,pkj->pj", np.sin(self.w @ x + self.phase), self.u)
        return make_T(rotvec_to_R(_saturate(v[1], np.deg2rad(c.drift_deg))), _saturate(v[0], c.drift_mm * 1e-3))

    def noise(self, step: int) -> tuple[np.ndarray, float]:
        """Frame ``step``'s noise: (``E_noise`` 4x4 in the jaw frame, jaw-angle noise rad)."""
        c = self.config
        if c.noise_mm == 0 and c.noise_deg == 0 and c.jaw_noise_deg == 0:
            return np.eye(4), 0.0
        rng = np.random.default_rng(self.key + (int(step),))
        d = rng.normal(size=7)
        return (make_T(rotvec_to_R(d[3:6] * np.deg2rad(c.noise_deg)), d[:3] * c.noise_mm * 1e-3),
                float(d[6] * np.deg2rad(c.jaw_noise_deg)))

    def report(self, T_world_jaw: np.ndarray, jaw_rad: float, step: int) -> tuple[np.ndarray, float]:
        """(reported ``T_world_jaw``, reported ``jaw_rad``) of the true ones in frame ``step``."""
        if self.config.exact:
            return np.asarray(T_world_jaw, float).copy(), float(jaw_rad)
        T = np.asarray(T_world_jaw, float)
        E_noise, jaw_noise = self.noise(step)
        T_rep = self.T_reg @ T @ self.configuration_error(T) @ E_noise
        return T_rep, float(np.clip(jaw_rad + self.jaw_offset_rad + jaw_noise, 0.0, np.pi))


def draw_arm_errors(config: Optional[ArmErrorConfig], key, first_jaws: dict) -> dict:
    """``{name: ArmError}`` for the arms of ``first_jaws`` (name -> first ``T_world_jaw``), the
    i-th (in the dict's order) drawn from ``(*key, 56, i)``; empty when ``config`` is exact."""
    if config is None or config.exact:
        return {}
    return {name: ArmError.draw(config, (*key, 56, i), T) for i, (name, T) in enumerate(first_jaws.items())}


def reported(arm_errors: dict, name: str, T_world_jaw: np.ndarray, jaw_rad: float, holds, step: int):
    """The ``InstrumentPose`` of instrument ``name`` as its arm reports it in frame ``step``, the
    truth in ``T_world_jaw_truth`` / ``jaw_rad_truth`` where the report differs from it."""
    err = arm_errors.get(name)
    T = np.asarray(T_world_jaw, float)
    if err is None:
        return InstrumentPose(T.copy(), float(jaw_rad), holds)
    T_rep, jaw_rep = err.report(T, jaw_rad, step)
    return InstrumentPose(T_rep, jaw_rep, holds, None if np.array_equal(T_rep, T) else T.copy(),
                          None if jaw_rep == float(jaw_rad) else float(jaw_rad))

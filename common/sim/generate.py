"""Dataset generation from the built-in scene: N needle poses x K endoscope poses, or N moving
takes of an instrument motion script (``motion``: ``common.sim.takes``), each as long as its script.

Sequence ``s`` of a run seeded ``seed`` depends only on (seed, s, steps, preset, image size), so a
run is reproducible, resumable after an interruption (finished sequences are kept) and can be
extended with more sequences. Sequences are rendered by worker processes (spawned, one GL
context each); the parent writes frames.jsonl in order.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from common.frames import CAMERAS
from common.geometry.ecm_kinematics import MULTIVIEW_STEP_RAD

FPS = 30.0
GENERATE_FILE = "generate.json"


@dataclass(frozen=True)
class GenerateConfig:
    sequences: int
    steps: int
    seed: int = 0
    randomise: str = "train"
    width: int = 1920
    height: int = 1080
    image_format: str = "jpg"
    jpeg_quality: int = 95
    msaa: int = 4
    step_rad: float = MULTIVIEW_STEP_RAD   # ECM joint step between a sequence's endoscope poses
    thread: str = "random"                 # "none": no suture thread drawn (a threadless twin)
    motion: str = "none"                   # "none": the multi-view protocol; else a take's script
    take_every: int = 1                    # keep every k-th frame of a take (training sets: more takes per hour)
    arm_error: str = "exact"               # how a take's arms report the jaws (common.sim.arm_error spec)

    def stable(self) -> dict:
        """What must match for a folder to be resumed or extended."""
        d = dict(self.__dict__)
        d.pop("sequences")
        if d["thread"] == "random":        # folders made before the option resume as they were
            d.pop("thread")
        if d["motion"] == "none":
            d.pop("motion")
        if d["take_every"] == 1:
            d.pop("take_every")
        if d["arm_error"] == "exact":
            d.pop("arm_error")
        return d

    def take_plan(self, take: int, meta, preset, tex: int = 1024):
        from common.sim.arm_error import arm_error_config
        from common.sim.takes import plan_take
        return plan_take(self.seed, take, self.motion, preset, meta.rig, meta.needle, meta.arm, tex, self.msaa,
                         thread=self.thread != "none", arm_error=arm_error_config(self.arm_error))


def scene_meta(width: int, height: int, source: str):
    """dataset.yaml contents of the built-in scene."""
    from common.data.dataset import DatasetMeta
    from common.geometry.camera import StereoRig
    from common.geometry.needle import NeedleModel
    from common.sim.randomise import default_arm
    return DatasetMeta((width, height), StereoRig.default(width, height), NeedleModel(), default_arm(), source)


def render_sequence(renderer, cfg: GenerateConfig, sequence: int) -> list[tuple[dict, dict, int]]:
    """Plan and render one sequence: per step (BGR images by camera, frame fields, JPEG quality)."""
    from common.sim.randomise import (
        degrade_stereo,
        get_preset,
        jpeg_quality,
        plan_sequence,
    )
    meta = scene_meta(cfg.width, cfg.height, "")
    preset = get_preset(cfg.randomise)
    tex = 1024
    if cfg.motion != "none":
        return _render_take(renderer, cfg, sequence, meta, preset, tex)
    plan = plan_sequence(cfg.seed, sequence, cfg.steps, preset, meta.rig, meta.needle, meta.arm, tex, cfg.msaa,
                         cfg.step_rad, thread=cfg.thread != "none")
    renderer.load(plan.spec)
    rng = np.random.default_rng(plan.image_seed)
    out = []
    for step, q in enumerate(plan.joints):
        T_world_ecm = meta.arm.T_world_ecm(q)
        renders = renderer.render(T_world_ecm)
        gt = renderer.ground_truth(T_world_ecm, renders)
        # JPEG artefacts come from the file's own compression when writing JPEG
        images = degrade_stereo({c: r.bgr for c, r in renders.items()}, rng, preset,
                                jpeg=cfg.image_format != "jpg", avoid=gt["keypoints"])
        quality = min(cfg.jpeg_quality, jpeg_quality(rng, preset))
        fields = {"sequence": sequence, "step": step, "ecm_joints": np.asarray(q, float),
                  "T_world_ecm": T_world_ecm, "T_world_needle": plan.spec.T_world_needle,
                  "keypoints": gt["keypoints"], "visible": gt["visible"], "bbox": gt["bbox"],
                  "arc_visible": gt["arc_visible"], "arc_seen": gt["arc_seen"]}
        out.append((images, fields, quality))
    return out


def _render_take(renderer, cfg: GenerateConfig, sequence: int, meta, preset, tex: int) -> list:
    from common.sim.randomise import degrade_stereo, jpeg_quality
    from common.sim.takes import render_take
    plan = cfg.take_plan(sequence, meta, preset, tex)
    rng = np.random.default_rng(plan.image_seed)
    out = []
    for images, fields in render_take(renderer, plan, meta.arm,
                                      lambda im, kp: degrade_stereo(im, rng, preset, jpeg=cfg.image_format != "jpg",
                                                                        avoid=kp),
                                      every=cfg.take_every):
        out.append((images, {"sequence": sequence, **fields}, min(cfg.jpeg_quality, jpeg_quality(rng, preset))))
    return out


def take_lengths(cfg: GenerateConfig) -> list[int]:
    """Frames of each of the run's sequences (``steps`` each, or each take's script)."""
    if cfg.motion == "none":
        return [cfg.steps] * cfg.sequences
    from common.sim.randomise import get_preset
    meta, preset = scene_meta(cfg.width, cfg.height, ""), get_preset(cfg.randomise)
    k = cfg.take_every
    return [-(-len(cfg.take_plan(s, meta, preset)) // k) for s in range(cfg.sequences)]


# ---------------------------------------------------------------- worker processes

_WORKER = {}


def _init_worker(cfg: GenerateConfig, folder: str, offsets: list) -> None:
    from common.sim.render import SceneRenderer
    _WORKER["renderer"] = SceneRenderer()
    _WORKER["cfg"], _WORKER["folder"], _WORKER["offsets"] = cfg, folder, offsets


def _work(sequence: int) -> list[dict]:
    """Render sequence ``sequence``, write its images; returns its frames.jsonl objects."""
    from common.data.dataset import Frame
    from common.data.writer import write_frame_images
    cfg, folder = _WORKER["cfg"], _WORKER["folder"]
    frames = []
    for i, (images, fields, quality) in enumerate(render_sequence(_WORKER["renderer"], cfg, sequence)):
        index = _WORKER["offsets"][sequence] + i
        paths = write_frame_images(folder, index, images, cfg.image_format, quality)
        fr = Frame(index=index, stamp_ns=int(round(index * 1e9 / FPS)), left=paths["left"],
                   right=paths["right"], **fields)
        frames.append(fr.to_json())
    return frames


def generate(folder: str, cfg: GenerateConfig, jobs: int = 2, progress: bool = True,
             overwrite: bool = False) -> int:
    """Generate (or resume, or extend) a dataset folder; returns the number of frames in it."""
    if not (np.isfinite(cfg.step_rad) and 0.0 <= cfg.step_rad <= 0.5):
        raise ValueError(f"dataset generate: --step-rad must be in [0, 0.5] rad, got {cfg.step_rad}")
    from common.sim.takes import TAKE_MOTIONS
    if cfg.take_every < 1 or (cfg.take_every > 1 and cfg.motion == "none"):
        raise ValueError(f"dataset generate: --take-every must be >= 1 and needs --motion, got {cfg.take_every}")
    if cfg.motion != "none" and cfg.motion not in TAKE_MOTIONS:
        raise ValueError(f"dataset generate: --motion must be none or one of {TAKE_MOTIONS}, got {cfg.motion!r}")
    from common.sim.arm_error import arm_error_config
    arm_error = arm_error_config(cfg.arm_error)              # a bad spec fails here, before any work
    if cfg.motion == "none" and not arm_error.exact:
        raise ValueError("dataset generate: --arm-error needs --motion (a multi-view folder states no instruments)")
    if cfg.arm_error != arm_error.spec():
        raise ValueError(f"dataset generate: arm_error {cfg.arm_error!r} is not canonical; "
                         f"use arm_error_config(...).spec(): {arm_error.spec()!r}")
    import multiprocessing as mp

    import mujoco
    from common.progress import progress_bar

    from common.data.writer import DatasetWriter, resume_generation
    # settings added later default to their old behaviour
    lengths = take_lengths(cfg)
    resume, done = resume_generation(folder, GENERATE_FILE, cfg.stable(), cfg.sequences, cfg.steps,
                                     "dataset generate", overwrite, GenerateConfig(1, 1).stable(), lengths)
    what = (f"steps={cfg.steps} step_rad={cfg.step_rad:g}" if cfg.motion == "none" else
            f"motion={cfg.motion} (moving takes)" + ("" if arm_error.exact else f" arm_error={cfg.arm_error}"))
    source = (f"needletrack dataset generate (MuJoCo {mujoco.__version__} built-in suturing scene): "
              f"randomise={cfg.randomise} seed={cfg.seed} {what}")
    offsets = [int(x) for x in np.concatenate([[0], np.cumsum(lengths)])]
    meta = scene_meta(cfg.width, cfg.height, source)
    writer = DatasetWriter(folder, meta, cfg.image_format, cfg.jpeg_quality, resume=resume)
    todo = list(range(done, cfg.sequences))
    bar = progress_bar(total=offsets[-1], initial=offsets[done], unit="frame",
               desc="generate", show=progress, smoothing=0.1)
    try:
        if jobs <= 1 or len(todo) <= 1:
            _init_worker(cfg, folder, offsets)
            results = map(_work, todo)
            _consume(results, writer, bar)
        else:
            ctx = mp.get_context("spawn")
            env_threads = os.environ.get("LP_NUM_THREADS")
            os.environ["LP_NUM_THREADS"] = env_threads or str(max(1, (os.cpu_count() or 2) // jobs))
            try:
                with ctx.Pool(jobs, initializer=_init_worker, initargs=(cfg, folder, offsets)) as pool:
                    _consume(pool.imap(_work, todo), writer, bar)
            finally:
                if env_threads is None:
                    os.environ.pop("LP_NUM_THREADS", None)
    finally:
        bar.close()
        writer.close()
    return writer.n_frames


def _consume(results, writer, bar) -> None:
    from common.data.dataset import parse_frame
    for frames in results:
        for obj in frames:
            writer.append(parse_frame(obj))
            bar.update(1)


def needle_free_scene(seed: int, frame: int, preset, meta, pale_thread: float | None = None):
    """(scene, T_world_ecm) of needle-free frame ``frame``: sequence ``frame`` of a run seeded
    ``seed`` under ``preset`` (a ``Preset``), its needle moved out of sight (the thread stays)."""
    from dataclasses import replace

    from common.sim.randomise import PALE_THREAD_RGB, THREAD_RGBS, plan_sequence
    plan = plan_sequence(seed, frame, 1, preset, meta.rig, meta.needle, meta.arm, 2048)
    T_hidden = plan.spec.T_world_needle.copy()
    T_hidden[:3, 3] = [0.0, 0.0, -5.0]
    spec = replace(plan.spec, T_world_needle=T_hidden)
    if pale_thread is not None:
        rng = np.random.default_rng([seed, frame, 1])
        dyed = [c for c in THREAD_RGBS if c != PALE_THREAD_RGB]
        rgb = PALE_THREAD_RGB if rng.random() < pale_thread else dyed[rng.integers(len(dyed))]
        spec = replace(spec, appearance=replace(spec.appearance, thread_rgb=rgb))
    return spec, meta.arm.T_world_ecm(plan.joints[0])


def generate_needle_free(folder, n_frames: int, seed: int = 777, preset: str = "test",
                         progress: bool = True, pale_thread: float | None = None,
                         width: int = 1920, height: int = 1080) -> Path:
    """Render ``n_frames`` stereo frames of the built-in scene with the needle moved out of sight
    (instruments, thread and tissue stay) as a dataset folder whose frames see no keypoint:
    negatives for training the detector and for measuring its false detections.

    ``pale_thread``: share of frames whose thread takes the palette's pale, needle-like colour
    (default: the preset's draw, 1 in 5) — a lone pale thread curled on the tissue is the
    decoy a detector most easily takes for a needle.

    Presets of the random looks (``random``, ``unseen``) make hard negatives: every instrument
    kind of their pool, jaws near the camera in most frames (``p_near`` 0.6; anywhere in the
    image, its centre too, where the needle would be), specular streaks in
    most (``p_streaks`` 0.8), threads without a needle, folds, cuts and stains on the pad; their
    frames also carry ``instruments`` (``psm1``..``psm4``: jaw frames and openings), so that a
    trainer can centre crops on the jaws."""
    from dataclasses import replace

    from common.progress import progress_bar

    from common.data.dataset import Frame
    from common.data.instruments import InstrumentPose
    from common.data.writer import DatasetWriter
    from common.sim.randomise import degrade_stereo, get_preset
    from common.sim.render import SceneRenderer
    folder = Path(folder)
    meta = scene_meta(width, height, f"needle-free frames, preset {preset}, seed {seed}")
    pre = get_preset(preset)
    if pre.pool:
        pre = replace(pre, p_near=0.6, p_streaks=0.8, near_over_needle=True)
    renderer = SceneRenderer()
    with DatasetWriter(str(folder), meta, "jpg", 95) as writer:
        for i in progress_bar(range(n_frames), desc="needle-free frames", unit="frame", show=progress):
            spec, T_world_ecm = needle_free_scene(seed, i, pre, meta, pale_thread)
            renderer.load(spec)
            renders = renderer.render(T_world_ecm)
            rng = np.random.default_rng([seed, i])
            images = degrade_stereo({c: r.bgr for c, r in renders.items()}, rng, pre)
            paths = writer.write_images(i, images)
            extra = {}
            if pre.pool:
                extra["instruments"] = {f"psm{k + 1}": InstrumentPose(ins.T_world_jaw, float(ins.jaw_open))
                                        for k, ins in enumerate(spec.instruments)}
            writer.append(Frame(index=i, stamp_ns=int(i * 33_333_333), left=paths["left"], right=paths["right"],
                                T_world_ecm=T_world_ecm,
                                visible={c: np.zeros(5, bool) for c in CAMERAS},
                                bbox={c: None for c in CAMERAS}, **extra))
    return folder

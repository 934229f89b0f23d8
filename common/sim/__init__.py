"""Simulated suturing scenes rendered into dataset folders, by two renderers sharing no code
(MuJoCo; the ``alt_`` modules: a NumPy/OpenCV z-buffer), and the ``needletrack dataset``
generators. Imports ``geometry`` and ``data``.

Modules (``python -m common.layout`` writes this list from their docstrings):

- ``alt_generate``: Dataset folders rendered by the second renderer (``common/sim/alt_render.py``),
  not by MuJoCo.
- ``alt_meshes``: The second renderer's triangle meshes (world or object frame, metres): the needle
  swept along its arc with a taper, a thread, boxes, instruments; their materials and labels.
- ``alt_raster``: The second renderer's z-buffer rasteriser: triangles in camera coordinates (OpenCV
  pinhole, pixel (0, 0) the centre of the top-left pixel) to per-sample depth, triangle and
  barycentrics.
- ``alt_render``: A second, independent renderer of stereo needle scenes: numpy/OpenCV, no MuJoCo,
  no GL.
- ``alt_tissue``: The second renderer's tissue: an analytic height field ``z = sum a sin(k .
- ``arm_error``: An arm's kinematic error: instruments reported as a dVRK reports them
  (docs/datasets.md).
- ``cli``: ``needletrack dataset generate|generate-alt|generate-negatives``: render dataset folders
  from the built-in scene or the second renderer (the other ``dataset`` subcommands:
  ``common.data.cli``, ``common.ros.cli``; the command itself: ``common.cli.dataset_main``).
- ``generate``: Dataset generation from the built-in scene: N needle poses x K endoscope poses, or N
  moving takes of an instrument motion script (``motion``: ``common.sim.takes``), each as long as
  its script.
- ``image_effects``: Image-space effects of the ``random`` looks, applied before the sensor model
  (``common.sim.randomise.degrade``): smoke or haze, glare (specular blobs) and specular streaks,
  defocus and motion blur, vignetting and white balance.
- ``instrument_kinds``: Instrument kinds of the ``random`` looks: each kind is a list of primitive
  parts (boxes, cylinders, capsules, spheres) on the instrument's body and on its two jaws.
- ``live``: The live simulator behind the ``sim`` node: scene, endoscope motion scripts and frames.
- ``look_textures``: Textures of the ``random`` looks: procedural patterns and photographs that
  scikit-image ships, recoloured through a palette, zoomed, turned, with blood-like stains and cut
  lines painted on.
- ``motion``: Instrument motion scripts of the built-in scene: the needle picked up, handed over and
  driven through the tissue by two patient-side instruments, ``psm1`` (from the left) and ``psm2``
  (from the right), at ``FPS`` frames a second.
- ``random_looks``: The ``random`` preset's looks, in which no look is special, and the held-out
  ``unseen`` family.
- ``randomise``: Random but physical scenes for the simulator: needle poses, endoscope poses,
  appearance, instruments and image degradations, under named presets.
- ``render``: Offscreen rendering of the suturing scene and its per-frame ground truth.
- ``scene``: The built-in suturing scene: an MJCF model with procedurally generated meshes and
  textures.
- ``scene_looks``: The scene's ``random`` looks: what a ``Look`` holds, the parts of the MJCF model
  that only a scene with a look has, and writing a look into the compiled model.
- ``scene_meshes``: The built-in scene's geometry: the tissue phantom's surface, tubes swept along a
  polyline, the needle's body and the suture thread's path.
- ``scene_textures``: The built-in scene's procedural textures: the tissue phantom's and the table's
  (RGB uint8, near white: the material's colour tints them), and a per-process cache of a few
  variants.
- ``takes``: Moving takes of the built-in scene: an instrument motion script (``common.sim.motion``)
  under an endoscope that stays still or drifts, rendered frame by frame with its ground truth.
- ``visibility``: What the rendered ground truth's ``visible`` means (``docs/dataset.md``), for both
  renderers (``common.sim.render``, ``common.sim.alt_render``).
"""

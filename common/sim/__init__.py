"""Simulated suturing scenes rendered into dataset folders. Imports ``geometry`` and ``data``.

``scene`` (its geometry ``scene_meshes``, textures ``scene_textures``), ``render`` (MuJoCo, offscreen EGL), ``randomise`` (presets; the ``random`` looks:
``random_looks``, ``look_textures``, ``instrument_kinds``, ``scene_looks``, ``image_effects``), ``generate`` (dataset
folders), ``live`` (the live simulator node's frames), ``motion`` (the instruments' scripts), ``takes`` (moving
takes); ``alt_meshes``, ``alt_tissue``, ``alt_raster``,
``alt_render`` and ``alt_generate`` (a
second renderer sharing no code with the first: NumPy/OpenCV z-buffer); ``cli`` (the
``needletrack dataset`` command: generate, generate-alt, check, show).
"""

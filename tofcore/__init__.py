"""tofcore — a physically based Time-of-Flight camera simulator in NumPy.

The public API, re-exported from one module per concept. The packages follow the data flow
(docs/architecture.md): ``scene`` → ``tracer`` → ``sensor`` → ``output``, with ``render`` on top and
``gpu`` holding the device kernels:

* :class:`Scene`, :func:`demo_scene` — triangle meshes in metres (``scene``, ``demo``)
* :class:`Material`, :class:`Texture` — near-IR surface parameters (``material``)
* :class:`Camera` — intrinsics, OpenCV distortion, thin lens (``camera``)
* :class:`LED` — IR emitters in the sensor frame (``led``)
* :class:`Ambient` — unmodulated background light (``ambient``)
* :func:`trace`, :func:`trace_progressive`, :class:`Transport` — the path tracer (``tracer``; the compiled
  tracer where it can run, ``compiled``)
* :func:`look_at` — sensor poses (``pose``)
* :class:`Sensor`, :func:`load_preset`, :func:`list_presets` — sensor models and presets (``sensor``, ``presets``)
* :class:`Modulation` — pulsed / square / sine correlation functions (``modulation``)
* :func:`render` → :class:`Frame` — the camera's output with ground truth (``render``, ``frame``)
* :func:`write_frame`, :func:`read_exr` — EXR, PNG, PLY, JSON and camera-file outputs (``writers``)
* :func:`load_mesh` — scenes from OBJ, PLY, glTF/GLB and STL files, through trimesh (``scene.mesh_files``)
* ``exr`` — tofcore's own OpenEXR codec (NumPy + zlib): ``exr.write``, ``exr.read``, ``exr.read_header``
* ``limits`` — resource limits checked before allocating (:class:`LimitError`)
"""

import sys as _sys

if _sys.argv[:1] == ["-m"] and "tofcore" in _sys.orig_argv[1:] \
        and _sys.orig_argv[_sys.orig_argv.index("tofcore") - 1] == "-m":  # `python -m tofcore`: Ctrl-C is one line
    try:
        from ._interrupt import hold_until_the_command_starts

        hold_until_the_command_starts()
    except KeyboardInterrupt:  # Ctrl-C while that small module loads: no handler of ours yet
        import os as _os

        _os.write(2, b"\ninterrupted (SIGINT): nothing was written\n")
        _os._exit(130)

from . import limits
from .constants import SPEED_OF_LIGHT_M_S
from .output import exr
from .errors import Cancelled, ConfigError, ExrError, LimitError, SceneError, TofError
from .output.frame import Frame, Reason
from .output.writers import read_exr, write_frame
from .render import render, render_progressive, trace, trace_progressive
from .scene.ambient import Ambient
from .scene.camera import Camera
from .scene.demo import demo_ambient, demo_scene, suggested_pose
from .scene.led import LED
from .scene.material import Material, Texture
from .scene.mesh_files import load_mesh
from .scene.pose import from_blender_matrix_world, look_at
from .scene.scene import Scene
from .sensor.config import Sensor
from .sensor.modulation import Modulation
from .sensor.presets import list_presets, load_preset
from .tracer.transport import FirstHit, Transport

__all__ = [
    "Ambient", "Camera", "Cancelled", "ConfigError", "ExrError", "FirstHit", "Frame", "LED", "LimitError", "Material",
    "Modulation",
    "Reason", "SPEED_OF_LIGHT_M_S", "Scene", "SceneError", "Sensor", "Texture", "TofError", "Transport", "demo_ambient", "demo_scene",
    "from_blender_matrix_world", "list_presets", "load_mesh", "load_preset", "look_at", "read_exr", "render",
    "render_progressive",
    "suggested_pose", "trace", "trace_progressive", "write_frame",
]
__version__ = "0.1.0"

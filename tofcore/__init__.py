"""tofcore — a physically based Time-of-Flight camera simulator in NumPy.

The public API, re-exported from one module per concept:

* :class:`Scene`, :func:`demo_scene` — triangle meshes in metres (``scene``, ``demo``)
* :class:`Material`, :class:`Texture` — near-IR surface parameters (``material``)
* :class:`Camera` — intrinsics, OpenCV distortion, thin lens (``camera``)
* :class:`LED` — IR emitters in the sensor frame (``led``)
* :class:`Ambient` — unmodulated background light (``ambient``)
* :func:`trace`, :func:`trace_progressive`, :class:`Transport` — the path tracer (``transport``)
* :func:`look_at` — sensor poses (``pose``)
* :class:`Sensor`, :func:`load_preset`, :func:`list_presets` — sensor models and presets (``sensor``, ``presets``)
* :class:`Modulation` — pulsed / square / sine correlation functions (``modulation``)
* :func:`render` → :class:`Frame` — the camera's output with ground truth (``render``, ``frame``)
* :func:`write_frame`, :func:`read_exr` — EXR, PNG, PLY and JSON outputs (``writers``)
* ``limits`` — resource limits checked before allocating (:class:`LimitError`)
"""

import sys as _sys

if _sys.argv[:1] == ["-m"] and "tofcore" in _sys.orig_argv[1:] \
        and _sys.orig_argv[_sys.orig_argv.index("tofcore") - 1] == "-m":  # `python -m tofcore`: Ctrl-C is one line
    from ._interrupt import hold_until_the_command_starts

    hold_until_the_command_starts()

from .ambient import Ambient
from .camera import Camera
from .demo import demo_scene, suggested_pose
from . import limits
from .errors import Cancelled, ConfigError, LimitError, SceneError, TofError
from .led import LED
from .material import Material, Texture
from .pose import from_blender_matrix_world, look_at
from .scene import Scene
from .transport import SPEED_OF_LIGHT_M_S, FirstHit, Transport, trace, trace_progressive
from .frame import Frame, Reason
from .modulation import Modulation
from .sensor import Sensor
from .presets import list_presets, load_preset
from .render import render, render_progressive
from .writers import read_exr, write_frame

__all__ = [
    "Ambient", "Camera", "Cancelled", "ConfigError", "FirstHit", "Frame", "LED", "LimitError", "Material", "Modulation",
    "Reason", "SPEED_OF_LIGHT_M_S", "Scene", "SceneError", "Sensor", "Texture", "TofError", "Transport", "demo_scene",
    "from_blender_matrix_world", "list_presets", "load_preset", "look_at", "read_exr", "render", "render_progressive",
    "suggested_pose", "trace", "trace_progressive", "write_frame",
]
__version__ = "0.1.0"

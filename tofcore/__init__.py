"""tofcore — a physically based Time-of-Flight camera simulator in NumPy.

The public API, re-exported from one module per concept:

* :class:`Scene`, :func:`demo_scene` — triangle meshes in metres (``scene``, ``demo``)
* :class:`Material`, :class:`Texture` — near-IR surface parameters (``material``)
* :class:`Camera` — intrinsics, OpenCV distortion, thin lens (``camera``)
* :class:`LED` — IR emitters in the sensor frame (``led``)
* :class:`Ambient` — unmodulated background light (``ambient``)
* :func:`trace`, :func:`trace_progressive`, :class:`Transport` — the path tracer (``transport``)
* :func:`look_at` — sensor poses (``pose``)
"""

from .ambient import Ambient
from .camera import Camera
from .demo import demo_scene, suggested_pose
from .errors import ConfigError, SceneError, TofError
from .led import LED
from .material import Material, Texture
from .pose import from_blender_matrix_world, look_at
from .scene import Scene
from .transport import SPEED_OF_LIGHT_M_S, FirstHit, Transport, trace, trace_progressive

__all__ = [
    "Ambient", "Camera", "ConfigError", "FirstHit", "LED", "Material", "SPEED_OF_LIGHT_M_S", "Scene",
    "SceneError", "Texture", "TofError", "Transport", "demo_scene", "from_blender_matrix_world", "look_at",
    "suggested_pose", "trace", "trace_progressive",
]
__version__ = "0.1.0"

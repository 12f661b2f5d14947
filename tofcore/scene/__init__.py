"""What is rendered: geometry, materials and their BSDFs, the BVH, the LEDs, ambient light, the camera and its pose.

Everything here is data and pure functions of it; nothing imports the tracer, the sensor or the outputs.
"""

from .ambient import Ambient
from .camera import Camera
from .led import LED
from .material import Material, Texture
from .scene import Scene

__all__ = ["Ambient", "Camera", "LED", "Material", "Scene", "Texture"]

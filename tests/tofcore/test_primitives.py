"""tofcore.scene.primitives: closed meshes with outward faces in the unit cube."""

import math

import numpy as np
import pytest

from tofcore.errors import ConfigError
from tofcore.scene.primitives import NAMES, primitive

#: Volumes of the shapes inscribed in the unit cube, and the relative shortfall of their polygon
#: versions at 24 segments and 12 rings (a polygon inscribed in a circle has area (n/2π) sin(2π/n) of it:
#: 1.1 % less at n = 24; the UV sphere's rings lose more).
VOLUMES = {"box": (1.0, 0.0), "cylinder": (math.pi / 4, 0.012), "sphere": (math.pi / 6, 0.03),
           "cone": (math.pi / 12, 0.012)}


@pytest.mark.parametrize("name", NAMES)
def test_primitives_are_closed_outward_and_fill_the_unit_cube(name):
    scene = primitive(name)
    v, t = scene.vertices.astype(np.float64), scene.triangles
    edges = {tuple(e) for e in np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]).tolist()}
    assert all((b, a) in edges for a, b in edges)  # every edge shared by two faces, opposite directions: closed
    volume = np.einsum("ij,ij->i", v[t[:, 0]], np.cross(v[t[:, 1]], v[t[:, 2]])).sum() / 6  # > 0: outward
    exact, shortfall = VOLUMES[name]
    assert exact * (1 - shortfall) - 1e-9 <= volume <= exact + 1e-9
    lo, hi = scene.bounds
    assert np.allclose(lo, -0.5) and np.allclose(hi, 0.5)
    assert scene.object_names == (name,) and scene.materials[0].name == name


def test_an_unknown_primitive_is_refused():
    with pytest.raises(ConfigError, match=r"primitive: name must be one of \['box', 'cylinder', 'sphere', 'cone'\], "
                                          r"got 'torus'"):
        primitive("torus")

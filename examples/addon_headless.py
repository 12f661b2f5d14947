"""Headless walk-through of the Blender extension with the bpy module: build a room corner with a box,
"Add ToF Camera" (Kinect v2), "Render ToF", save the four result images to out/addon/.

Usage: BLENDER_USER_RESOURCES=/tmp/b XDG_CONFIG_HOME=/tmp/b XDG_CACHE_HOME=/tmp/b \
       .venv/bin/python examples/addon_headless.py WIDTH HEIGHT SPP     (e.g. 512 424 32)
"""
import sys, os, time, math
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), '..'))
import bpy, numpy as np
bpy.ops.wm.read_factory_settings(use_empty=True)
import addon
from addon import operators, images
addon.register()

def add_mesh(name, verts, faces, loc=(0, 0, 0)):
    me = bpy.data.meshes.new(name); me.from_pydata(verts, [], faces); me.update()
    ob = bpy.data.objects.new(name, me); ob.location = loc; bpy.context.scene.collection.objects.link(ob); return ob

add_mesh("Floor", [(-2, -1, 0), (2, -1, 0), (2, 3, 0), (-2, 3, 0)], [(0, 1, 2, 3)])
add_mesh("Back Wall", [(-2, 1.5, 0), (2, 1.5, 0), (2, 1.5, 2.5), (-2, 1.5, 2.5)], [(0, 1, 2, 3)])
add_mesh("Side Wall", [(1.2, -1, 0), (1.2, 3, 0), (1.2, 3, 2.5), (1.2, -1, 2.5)], [(0, 1, 2, 3)])
h = 0.25
corners = [(x, y, z) for z in (-h, h) for y in (-h, h) for x in (-h, h)]
faces = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
add_mesh("Box", corners, faces, loc=(0.2, 0.6, h))

bpy.ops.tof.add_camera(preset='kinect_v2', location=(-0.3, -1.6, 1.1), rotation=(math.radians(65), 0, math.radians(-12)))
cam = bpy.context.scene.camera
s = cam.data.tof
s.use_resolution = True; s.width, s.height = int(sys.argv[-3]), int(sys.argv[-2])
s.spp = int(sys.argv[-1]); s.max_depth = 4; s.output_dir = "out/addon"
t = time.time()
passes = []
orig = operators._apply_pass
def rec(frame):
    orig(frame); passes.append((frame.stats["spp"], frame.stats["convergence"][-1]["est_depth_error_m"], time.time() - t))
operators._apply_pass = rec
print(bpy.ops.tof.render('INVOKE_DEFAULT'), f"{time.time() - t:.1f} s")
for p in passes: print("pass", p)
for name in images.IMAGE_NAMES.values():
    im = bpy.data.images[name]
    im.filepath_raw = f"out/addon/{name.replace(' ', '_')}.png"; im.file_format = 'PNG'; im.save()
print(operators.last_result["limits"])

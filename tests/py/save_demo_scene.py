"""Saves the Blender worker's built-in demo scene as a .blend, for tests/blender_worker.rs, which
then renders it as a user's scene file (``blender -b scene.blend`` or ``--blend scene.blend``):

    blender -b --factory-startup --python save_demo_scene.py -- WORKER_DIR OUT.blend
    python save_demo_scene.py WORKER_DIR OUT.blend        (Blender as a Python module)
"""

import sys

import bpy

args = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
worker_dir, out = args
sys.path.insert(0, worker_dir)
import blender_worker  # noqa: E402 - from worker_dir

blender_worker.demo_scene(bpy.context.scene)
bpy.ops.wm.save_as_mainfile(filepath=out)
print(f"saved {out} with Blender {bpy.app.version_string}")

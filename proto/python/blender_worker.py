"""A splatd render worker that runs inside Blender and renders Cycles passes.

    blender -b scene.blend --python blender_worker.py -- --url URL --frame ID --passes N

Every pass is a full Cycles render whose pixels are each an independent sample of that pixel's
box-filtered estimator, which is what splatd's reweighting needs:

* distinct seeds: pass k renders with ``cycles.seed`` derived from (``--seed``, k);
* independent sub-pixel positions: Cycles puts a pass's first sample at the same sub-pixel
  position whatever its seed, so the worker uses a near-point pixel filter (box, 0.01 px) and
  shifts the camera by a random sub-pixel offset drawn from the pass's seed; over many passes
  each pixel is sampled uniformly over its area (a box filter), not at one fixed point;
* clamping, denoising and adaptive sampling are off, so nothing is clipped, blurred or stopped
  early; any ``--spp`` per pass (each pass is then the mean of its samples at one position).

Each pass is written as an OpenEXR (32-bit float, ZIP, linear) and posted with the
``splatd_client`` package (``pip install ./proto/python`` into the Python Blender uses, or point
``PYTHONPATH`` at an environment that has it and run Blender with ``--python-use-system-env``).
The frame is created with create-or-get, so a ``write`` token (``--token`` or ``SPLATD_TOKEN``)
is enough. A pass is posted as ``(worker, seq = pass number)``: rerunning the same passes with
the same ``--worker`` adds nothing twice.

``--aovs albedo,normal,depth`` renders those Cycles passes too (diffuse colour, normal, depth)
and sends them with every pass: the pass is written as a multilayer EXR (``ViewLayer.Combined``
is the beauty, ``ViewLayer.DiffCol``, ``ViewLayer.Normal`` and ``ViewLayer.Depth`` the AOVs, named
after the scene's active view layer, which is the only one rendered), and the frame is created
with those layers declared, so the server serves their means beside the reweighted beauty (for a
denoiser). A frame that already exists must have been created with the same AOVs.

``--demo-scene`` replaces the scene with a tiny built-in one (32x24: a diffuse floor and wall, a
sphere, and an emitting sphere less than a pixel across that lights them), and ``--reference SPP --output
PATH`` renders one image of the scene with a 1-pixel box filter at SPP samples instead of
posting passes, for comparing the passes' mean with.
"""

import argparse
import math
import os
import random
import sys
import tempfile

import bpy

try:
    import splatd_client as sc
except ImportError:  # pragma: no cover - depends on the environment
    sys.exit("blender_worker.py needs the splatd client: pip install ./proto/python into "
             "Blender's Python, or PYTHONPATH=... blender --python-use-system-env")


# `--aovs` names: the view layer's switch, the layer Blender writes, and its channels.
AOV_PASSES = {
    "albedo": ("use_pass_diffuse_color", "DiffCol", ["R", "G", "B"]),
    "normal": ("use_pass_normal", "Normal", ["X", "Y", "Z"]),
    "depth": ("use_pass_z", "Depth", ["Z"]),
}


def aov_list(text):
    """``--aovs``: comma-separated names of ``AOV_PASSES``, each at most once."""
    names = [n.strip() for n in text.split(",") if n.strip()]
    unknown = [n for n in names if n not in AOV_PASSES]
    if unknown or len(set(names)) != len(names):
        raise argparse.ArgumentTypeError(
            f"--aovs takes distinct names among {', '.join(AOV_PASSES)}, not {text!r}")
    return names


def parse_args(argv):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--url", default="http://127.0.0.1:7878")
    p.add_argument("--frame", help="frame id (default: the scene's name)")
    p.add_argument("--token", default=os.environ.get("SPLATD_TOKEN"))
    p.add_argument("--passes", type=int, default=16)
    p.add_argument("--first-pass", type=int, default=0)
    p.add_argument("--spp", type=int, default=1, help="Cycles samples per pass")
    p.add_argument("--seed", type=int, default=0, help="seeds of pass k derive from (seed, k)")
    p.add_argument("--worker", type=int, default=None,
                   help="worker id (default: derived from --seed, so reruns match)")
    p.add_argument("--resolution", type=int, nargs=2, metavar=("W", "H"))
    p.add_argument("--keep-dir", help="keep each pass's EXR here (pass_K.exr)")
    p.add_argument("--aovs", type=aov_list, default=[],
                   help=f"Cycles passes to send with the beauty: some of {','.join(AOV_PASSES)}")
    p.add_argument("--demo-scene", action="store_true")
    p.add_argument("--reference", type=int, metavar="SPP",
                   help="render one box-filtered image at SPP samples to --output instead")
    p.add_argument("--output", help="where --reference writes its EXR")
    return p.parse_args(argv)


def demo_scene(scene):
    """A tiny scene with a small light: the case where a fixed sub-pixel position is biased."""
    for obj in list(bpy.data.objects):
        bpy.data.objects.remove(obj, do_unlink=True)
    world = bpy.data.worlds.new("splatd-demo") if scene.world is None else scene.world
    scene.world = world
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.05

    def diffuse(name, rgb):
        mat = bpy.data.materials.new(name)
        mat.use_nodes = True
        bsdf = mat.node_tree.nodes["Principled BSDF"]
        bsdf.inputs["Base Color"].default_value = (*rgb, 1.0)
        bsdf.inputs["Specular"].default_value = 0.0
        bsdf.inputs["Roughness"].default_value = 1.0
        return mat

    bpy.ops.mesh.primitive_plane_add(size=8.0, location=(0.0, 0.0, 0.0))
    bpy.context.object.data.materials.append(diffuse("floor", (0.8, 0.8, 0.8)))
    bpy.ops.mesh.primitive_plane_add(size=8.0, location=(0.0, 2.0, 2.0), rotation=(math.pi / 2, 0, 0))
    bpy.context.object.data.materials.append(diffuse("wall", (0.2, 0.4, 0.8)))
    bpy.ops.mesh.primitive_uv_sphere_add(radius=0.5, location=(-0.4, 0.6, 0.5))
    bpy.context.object.data.materials.append(diffuse("sphere", (0.8, 0.3, 0.2)))
    # The lamp: a small, very bright emitting sphere seen directly by the camera, less than a
    # pixel across (0.1 m, where a pixel is about 0.1 m), which also lights the scene.
    bpy.ops.mesh.primitive_uv_sphere_add(radius=0.05, location=(0.55, 0.4, 1.1))
    lamp = bpy.data.materials.new("lamp")
    lamp.use_nodes = True
    nodes = lamp.node_tree.nodes
    nodes.remove(nodes["Principled BSDF"])
    emission = nodes.new("ShaderNodeEmission")
    emission.inputs["Strength"].default_value = 2000.0
    lamp.node_tree.links.new(emission.outputs["Emission"], nodes["Material Output"].inputs["Surface"])
    bpy.context.object.data.materials.append(lamp)
    cam = bpy.data.cameras.new("camera")
    cam_obj = bpy.data.objects.new("camera", cam)
    cam_obj.location = (0.0, -4.0, 1.2)
    cam_obj.rotation_euler = (math.radians(85.0), 0.0, 0.0)
    scene.collection.objects.link(cam_obj)
    scene.camera = cam_obj
    scene.render.resolution_x, scene.render.resolution_y = 32, 24


def configure(scene, resolution, spp):
    """Cycles on the CPU, nothing that changes the estimator, linear float EXR output."""
    scene.render.engine = "CYCLES"
    c = scene.cycles
    c.device = "CPU"
    c.samples = spp
    c.use_adaptive_sampling = False
    c.use_denoising = False
    c.sample_clamp_direct = 0.0
    c.sample_clamp_indirect = 0.0
    c.use_animated_seed = False
    if resolution:
        scene.render.resolution_x, scene.render.resolution_y = resolution
    scene.render.resolution_percentage = 100
    scene.render.pixel_aspect_x = scene.render.pixel_aspect_y = 1.0
    scene.render.use_border = False
    scene.render.film_transparent = False
    scene.render.use_compositing = False
    scene.render.use_sequencer = False
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    scene.view_settings.gamma = 1.0
    settings = scene.render.image_settings
    settings.file_format = "OPEN_EXR"
    settings.color_mode = "RGB"
    settings.color_depth = "32"
    settings.exr_codec = "ZIP"


def enable_aovs(scene, names):
    """Turns on the Cycles passes `names` in the active view layer and switches the output to a
    multilayer EXR; returns the layers as the frame declares them: ``(layer, [channels])``."""
    layer = bpy.context.view_layer
    for name in names:
        switch, _, _ = AOV_PASSES[name]
        setattr(layer, switch, True)
    scene.render.image_settings.file_format = "OPEN_EXR_MULTILAYER"
    return [(f"{layer.name}.{AOV_PASSES[n][1]}", AOV_PASSES[n][2]) for n in names]


def pass_seeds(seed, k):
    """Cycles' seed and the camera's sub-pixel shift (in pixels, in [-0.5, 0.5)) of pass k."""
    rng = random.Random(f"splatd-blender {seed} {k}")
    return rng.randrange(1 << 31), rng.random() - 0.5, rng.random() - 0.5


def render(scene, path, layer=None):
    """Renders the scene (only view layer `layer`, if given) to `path`; returns the file."""
    scene.render.filepath = path
    if layer:
        bpy.ops.render.render(write_still=True, layer=layer)
    else:
        bpy.ops.render.render(write_still=True)
    with open(path, "rb") as f:
        return f.read()


def main(argv):
    args = parse_args(argv)
    scene = bpy.context.scene
    if args.demo_scene:
        demo_scene(scene)
    configure(scene, args.resolution, args.spp)
    width, height = scene.render.resolution_x, scene.render.resolution_y
    camera = scene.camera
    if camera is None:
        sys.exit("the scene has no camera")

    if args.reference:
        if not args.output:
            sys.exit("--reference needs --output")
        scene.cycles.samples = args.reference
        scene.cycles.pixel_filter_type = "BOX"
        scene.cycles.filter_width = 1.0
        scene.cycles.seed = args.seed
        render(scene, os.path.abspath(args.output))
        print(f"reference: {width}x{height} at {args.reference} spp -> {args.output}")
        return

    # A near-point pixel filter: each pass samples one position per pixel, moved below.
    scene.cycles.pixel_filter_type = "BOX"
    scene.cycles.filter_width = 0.01
    # Camera shift is in units of the larger image side; one pixel is 1 / max(W, H).
    base_x, base_y = camera.data.shift_x, camera.data.shift_y
    per_pixel = 1.0 / max(width, height)
    frame = args.frame or scene.name
    worker = args.worker if args.worker is not None else random.Random(args.seed).getrandbits(53)
    client = sc.Client(args.url, token=args.token)
    aovs = enable_aovs(scene, args.aovs) if args.aovs else None
    # With AOVs the output is multilayer: render only the active view layer, whose Combined
    # layer is then the only candidate for the beauty.
    only = bpy.context.view_layer.name if aovs else None
    client.create_or_get(frame, width, height, aovs=aovs)
    keep = args.keep_dir or tempfile.mkdtemp(prefix="splatd-blender-")
    os.makedirs(keep, exist_ok=True)
    for k in range(args.first_pass, args.first_pass + args.passes):
        seed, dx, dy = pass_seeds(args.seed, k)
        scene.cycles.seed = seed
        camera.data.shift_x = base_x + dx * per_pixel
        # Image rows go down, the camera's y up: a shift of +dy pixels downwards is -dy.
        camera.data.shift_y = base_y - dy * per_pixel
        exr = render(scene, os.path.join(keep, f"pass_{k}.exr"), only)
        ack = client.post_pass(frame, worker, k, exr)
        print(f"pass {k}: seed {seed}, shift ({dx:+.3f}, {dy:+.3f}) px, "
              f"{ack['accepted']} samples{' (already there)' if ack['duplicate'] else ''}")
    camera.data.shift_x, camera.data.shift_y = base_x, base_y
    client.sync(frame)


if __name__ == "__main__":
    main(sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else [])

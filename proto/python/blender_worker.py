"""A splatd render worker that renders Cycles passes with Blender and posts them to a server.

Inside Blender (tested: 3.4 and, as the bpy module, 5.0.1), arguments after ``--``::

    blender -b scene.blend --python-exit-code 1 --python blender_worker.py -- --url URL --frame ID --passes N

or as a plain Python program with Blender as a Python module (PyPI's ``bpy``, which needs the
CPython version its wheel was built for: 3.11 for Blender 4.x and 5.0)::

    python blender_worker.py --blend scene.blend --url URL --frame ID --passes N

Every pass is a full Cycles render whose pixels are each an independent sample of that pixel's
box-filtered estimator, which is what splatd's reweighting needs:

* distinct seeds: the Cycles seed of a pass is drawn from the worker's id and the pass's number;
* independent sub-pixel positions: Cycles puts a pass's first sample at the same sub-pixel
  position whatever its seed, so the worker uses a near-point pixel filter (box, 0.01 px) and
  shifts the camera by a random sub-pixel offset drawn with the seed; over many passes each
  pixel is sampled uniformly over its area (a box filter), not at one fixed point;
* clamping, denoising and adaptive sampling are off, so nothing is clipped, blurred or stopped
  early; any ``--spp`` per pass (each pass is then the mean of its samples at one position).

Each pass is written as an OpenEXR (32-bit float, ZIP, linear) and posted with the
``splatd_client`` package (``pip install ./proto/python`` into the Python Blender runs: Blender's
bundled Python, the system's for Debian's Blender, the bpy module's environment; or point
``PYTHONPATH`` at an environment that has it and run Blender with ``--python-use-system-env``)
through its ``Outbox``, which keeps every pass until the server has it on disk and resends what a
server restart lost. The frame is created with create-or-get, so a ``write`` token (``--token``
or ``SPLATD_TOKEN``) is enough, and a frame that exists must have the scene's size and AOVs.

The scene: the ``.blend`` Blender opened, or ``--blend PATH``; ``--scene-script PY`` runs a
Python file that builds or changes it (after ``--blend``), ``--demo-scene`` replaces it with a
tiny built-in one (32x24: a diffuse floor and wall, a sphere, and an emitting sphere less than a
pixel across that lights them). Without any of them the worker refuses to render Blender's
startup file (which is what Blender falls back to when a ``.blend`` cannot be read).

Several machines: ``--job-index I --job-count N`` (as a farm manager hands out tasks) makes this
process job I of N: it renders its share of the ``--passes`` budget (N shares as equal as whole
passes allow) under a worker id of its own, drawn from (``--seed``, I, N) unless ``--worker``
gives one, and numbers its passes from ``--first-pass`` (0; give the next free number to add
passes to a frame this job rendered before). A pass's seeds are drawn from (worker id, pass
number), so two passes are the same samples only when they carry the same ``(worker, seq)``,
which the server counts once: jobs never overlap, a job run twice adds nothing twice (the
worker says so when the server answers that a pass was already there), and no way of running
the worker posts one pass's samples twice under different ids.

``--until-converged`` asks the server whether the frame has converged (its
``convergence.converged``, PROTOCOL.md) before the first pass, and after each pass it posts
while it renders the next one, and stops when it has; ``--passes`` is then the budget. The
verdict on a frame other workers keep changing waits for the frame's next render (seconds on
a busy server), so the worker never waits for it between passes: the pass rendered while the
server judged is posted only if the frame had not converged, so that the frame ends as it
was judged (one render of a job's last pass may go unused). A job that spends its budget
first says what the frame still waits on (``convergence.waiting_on``): pixels without samples,
energy the resolve removes, or each pixel's own samples. Reading a frame needs a token with the
``read`` role as well (roles ``read,write``).

``--aovs albedo,normal,depth`` renders those Cycles passes too (diffuse colour, normal, depth)
and sends them with every pass: the pass is written as a multilayer EXR and the frame is created
with those layers declared, so the server serves their means beside the reweighted beauty (for a
denoiser). The layer names are the ones the Blender in hand gives its passes (Cycles' own pass
list: ``ViewLayer.DiffCol`` on 3.4, ``ViewLayer.Diffuse Color`` on 5.0), checked against
the first pass's EXR header before anything is posted.

``--reference SPP --output PATH`` renders one image of the scene with a 1-pixel box filter at
SPP samples instead of posting passes, for comparing the passes' mean with.

Passes are written to a temporary folder removed at the end, or kept in ``--keep-dir``
(``pass_K.exr``). Wrong use (arguments that do not parse, a missing scene, a frame that exists
with another size, a refused pass) is an error with a message and a non-zero exit status.
"""

import argparse
import concurrent.futures
import hashlib
import math
import os
import random
import runpy
import shutil
import struct
import sys
import tempfile
import traceback

try:
    import bpy
except ImportError:  # pragma: no cover - depends on the environment
    sys.exit("blender_worker.py runs inside Blender (blender -b scene.blend --python "
             "blender_worker.py -- ARGS) or with Blender as a Python module (pip install bpy)")

try:
    import splatd_client as sc
except ImportError:  # pragma: no cover - depends on the environment
    sys.exit("blender_worker.py needs the splatd client: pip install ./proto/python into the "
             "Python Blender runs, or PYTHONPATH=... blender --python-use-system-env")

# Blender as a Python module (the bpy wheel) has no executable of its own: its arguments are
# the script's. Read before anything could set it.
AS_MODULE = bpy.app.binary_path == ""

# `--aovs` names: the view layer's switch of the Cycles pass. Its name and channels are the
# ones the Blender in hand registers (see `cycles_passes`).
AOV_SWITCHES = {
    "albedo": "use_pass_diffuse_color",
    "normal": "use_pass_normal",
    "depth": "use_pass_z",
}

# Worker ids travel as JSON numbers: below 2^53 they stay exact as doubles.
WORKER_BITS = 53


class WorkerError(Exception):
    """Wrong use or a refusal: reported as one line, exit status 1."""


def aov_list(text):
    """``--aovs``: comma-separated names of ``AOV_SWITCHES``, each at most once."""
    names = [n.strip() for n in text.split(",") if n.strip()]
    unknown = [n for n in names if n not in AOV_SWITCHES]
    if not names or unknown or len(set(names)) != len(names):
        raise argparse.ArgumentTypeError(
            f"--aovs takes distinct names among {', '.join(AOV_SWITCHES)}, not {text!r}")
    return names


def positive(text):
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, not {value}")
    return value


def natural(text):
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be at least 0, not {value}")
    return value


def parse_args(argv):
    p = argparse.ArgumentParser(
        prog="blender_worker.py", description=__doc__.splitlines()[0],
        epilog="Inside Blender the arguments follow `--`; with the bpy module they are the "
               "script's own.")
    p.add_argument("--url", default="http://127.0.0.1:7878")
    p.add_argument("--frame", help="frame id (default: the scene's name)")
    p.add_argument("--token", default=os.environ.get("SPLATD_TOKEN"),
                   help="a `write` token (default: $SPLATD_TOKEN)")
    p.add_argument("--blend", help="open this .blend file (with the bpy module, the scene)")
    p.add_argument("--scene-script", metavar="PY",
                   help="run this Python file to build or change the scene (after --blend)")
    p.add_argument("--demo-scene", action="store_true",
                   help="replace the scene with a tiny built-in one")
    p.add_argument("--passes", type=natural, default=16,
                   help="passes to render, over all jobs (with --until-converged: at most)")
    p.add_argument("--first-pass", type=natural, default=0,
                   help="number of this job's first pass (continue an earlier run from there)")
    p.add_argument("--job-index", type=natural, default=0,
                   help="this process is job I (from 0) of --job-count")
    p.add_argument("--job-count", type=positive, default=1,
                   help="number of jobs (machines, farm tasks) sharing the frame")
    p.add_argument("--until-converged", action="store_true",
                   help="stop as soon as the server says the frame has converged")
    p.add_argument("--spp", type=positive, default=1, help="Cycles samples per pass")
    p.add_argument("--seed", type=natural, default=0,
                   help="draws the worker id (with the job index and count)")
    p.add_argument("--worker", type=natural, default=None,
                   help="worker id below 2^53 (default: drawn from --seed and the job)")
    p.add_argument("--resolution", type=positive, nargs=2, metavar=("W", "H"))
    p.add_argument("--keep-dir", help="keep each pass's EXR here (pass_K.exr)")
    p.add_argument("--aovs", type=aov_list, default=[],
                   help=f"Cycles passes to send with the beauty: some of {','.join(AOV_SWITCHES)}")
    p.add_argument("--reference", type=positive, metavar="SPP",
                   help="render one box-filtered image at SPP samples to --output instead")
    p.add_argument("--output", help="where --reference writes its EXR")
    args = p.parse_args(argv)
    if args.job_index >= args.job_count:
        p.error(f"--job-index {args.job_index} is not below --job-count {args.job_count} "
                "(jobs are numbered from 0)")
    if args.worker is not None and args.worker >= 1 << WORKER_BITS:
        p.error(f"--worker {args.worker} is not below 2^{WORKER_BITS}")
    if args.reference and not args.output:
        p.error("--reference needs --output")
    if args.output and not args.reference:
        p.error("--output is for --reference")
    if args.frame is not None:
        try:
            sc.validate_frame_id(args.frame)
        except sc.WireError as e:
            p.error(f"--frame: {e}")
    return args


def worker_argv(argv):
    """The worker's own arguments: those after ``--`` inside Blender (whose own arguments come
    first), the script's with the bpy module."""
    if AS_MODULE:
        rest = argv[1:]
        return rest[1:] if rest[:1] == ["--"] else rest
    if "--" not in argv:
        raise WorkerError("inside Blender the worker's arguments follow `--` (blender -b "
                          "scene.blend --python blender_worker.py -- --url URL ...); there is no "
                          "`--`, so none were given (a lone `--` takes every default)")
    return argv[argv.index("--") + 1:]


def job_share(passes, index, count):
    """How many of `passes` job `index` of `count` renders: the shares differ by at most one."""
    return passes // count + (1 if index < passes % count else 0)


def default_worker(seed, index, count):
    """The worker id of job `index` of `count` under `seed`: the same on every rerun."""
    digest = hashlib.sha256(f"splatd-blender worker {seed} {index} {count}".encode()).digest()
    return int.from_bytes(digest[:8], "little") >> (64 - WORKER_BITS)


def pass_seeds(worker, k):
    """Cycles' seed and the camera's sub-pixel shift (in pixels, in [-0.5, 0.5)) of pass k of
    `worker`."""
    rng = random.Random(f"splatd-blender {worker} {k}")
    return rng.randrange(1 << 31), rng.random() - 0.5, rng.random() - 0.5


def node_tree(block):
    """The shader nodes of a material or world (``use_nodes`` is always on from Blender 5)."""
    if bpy.app.version < (5, 0, 0):
        block.use_nodes = True
    return block.node_tree


def shader_material(name, kind, **inputs):
    """A material whose surface is one shader node of `kind` with these input values; the same
    on every Blender (no default Principled BSDF, whose inputs changed in 4.0)."""
    mat = bpy.data.materials.new(name)
    tree = node_tree(mat)
    tree.nodes.clear()
    out = tree.nodes.new("ShaderNodeOutputMaterial")
    shader = tree.nodes.new(kind)
    for key, value in inputs.items():
        shader.inputs[key].default_value = value
    tree.links.new(shader.outputs[0], out.inputs["Surface"])
    return mat


def demo_scene(scene):
    """A tiny scene with a small light: the case where a fixed sub-pixel position is biased."""
    for obj in list(bpy.data.objects):
        bpy.data.objects.remove(obj, do_unlink=True)
    world = bpy.data.worlds.new("splatd-demo") if scene.world is None else scene.world
    scene.world = world
    tree = node_tree(world)
    tree.nodes.clear()
    background = tree.nodes.new("ShaderNodeBackground")
    background.inputs["Strength"].default_value = 0.05
    tree.links.new(background.outputs[0], tree.nodes.new("ShaderNodeOutputWorld").inputs["Surface"])

    def diffuse(name, rgb):
        return shader_material(name, "ShaderNodeBsdfDiffuse", Color=(*rgb, 1.0))

    bpy.ops.mesh.primitive_plane_add(size=8.0, location=(0.0, 0.0, 0.0))
    bpy.context.object.data.materials.append(diffuse("floor", (0.8, 0.8, 0.8)))
    bpy.ops.mesh.primitive_plane_add(size=8.0, location=(0.0, 2.0, 2.0), rotation=(math.pi / 2, 0, 0))
    bpy.context.object.data.materials.append(diffuse("wall", (0.2, 0.4, 0.8)))
    bpy.ops.mesh.primitive_uv_sphere_add(radius=0.5, location=(-0.4, 0.6, 0.5))
    bpy.context.object.data.materials.append(diffuse("sphere", (0.8, 0.3, 0.2)))
    # The lamp: a small, very bright emitting sphere seen directly by the camera, less than a
    # pixel across (0.1 m, where a pixel is about 0.1 m), which also lights the scene.
    bpy.ops.mesh.primitive_uv_sphere_add(radius=0.05, location=(0.55, 0.4, 1.1))
    bpy.context.object.data.materials.append(
        shader_material("lamp", "ShaderNodeEmission", Strength=2000.0))
    cam = bpy.data.cameras.new("camera")
    cam_obj = bpy.data.objects.new("camera", cam)
    cam_obj.location = (0.0, -4.0, 1.2)
    cam_obj.rotation_euler = (math.radians(85.0), 0.0, 0.0)
    scene.collection.objects.link(cam_obj)
    scene.camera = cam_obj
    scene.render.resolution_x, scene.render.resolution_y = 32, 24


def open_scene(args):
    """Opens, builds or checks the scene the worker renders; returns it."""
    if args.blend:
        path = os.path.abspath(args.blend)
        if not os.path.isfile(path):
            raise WorkerError(f"--blend {args.blend}: no such file")
        try:
            bpy.ops.wm.open_mainfile(filepath=path)
        except RuntimeError as e:
            raise WorkerError(f"--blend {args.blend}: Blender could not open it: {e}") from None
    elif not (bpy.data.filepath or args.demo_scene or args.scene_script):
        raise WorkerError(
            "no scene: Blender has no .blend file open (it falls back to its startup file when "
            "the one it was given cannot be read); give one (blender -b scene.blend ..., or "
            "--blend scene.blend), or --scene-script or --demo-scene")
    if args.scene_script:
        if not os.path.isfile(args.scene_script):
            raise WorkerError(f"--scene-script {args.scene_script}: no such file")
        runpy.run_path(args.scene_script, run_name="__main__")
    scene = bpy.context.scene
    if args.demo_scene:
        demo_scene(scene)
    return scene


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
    set_output(scene.render.image_settings, multilayer=False)


def set_output(settings, multilayer):
    """32-bit float ZIP OpenEXR, one RGB image or every pass of the view layer as layers.
    Blender 5 chooses the kind of output (``media_type``) before the format."""
    if hasattr(settings, "media_type"):
        settings.media_type = "MULTI_LAYER_IMAGE" if multilayer else "IMAGE"
    settings.file_format = "OPEN_EXR_MULTILAYER" if multilayer else "OPEN_EXR"
    if not multilayer:
        settings.color_mode = "RGB"
    settings.color_depth = "32"
    settings.exr_codec = "ZIP"


def cycles_passes(scene, layer):
    """The passes Cycles renders for `layer` as it is set up now: ``{name: channels}``, in
    Blender's own names (from Cycles' add-on, which registers them with the render result)."""
    import cycles.engine

    return {name: list(chans) for name, chans, _ in cycles.engine.list_render_passes(scene, layer)}


def enable_aovs(scene, names):
    """Turns on the Cycles passes `names` in the active view layer, one at a time to learn each
    one's name and channels from Cycles, and switches the output to a multilayer EXR. Returns the
    beauty's layer and the AOV layers as the frame declares them: ``(layer, [channels])``."""
    layer = bpy.context.view_layer
    layer.cycles.denoising_store_passes = False
    before = cycles_passes(scene, layer)
    combined = next(iter(before))  # Cycles lists the combined pass first
    aovs = []
    for name in names:
        setattr(layer, AOV_SWITCHES[name], True)
        now = cycles_passes(scene, layer)
        new = [(n, c) for n, c in now.items() if n not in before]
        if len(new) != 1:
            raise WorkerError(f"--aovs {name}: turning on {AOV_SWITCHES[name]} added "
                              f"{len(new)} Cycles passes ({', '.join(n for n, _ in new)}), not one")
        aovs.append((f"{layer.name}.{new[0][0]}", new[0][1]))
        before = now
    set_output(scene.render.image_settings, multilayer=True)
    return f"{layer.name}.{combined}", aovs


def exr_layers(data):
    """The layers of an OpenEXR file, read from its headers: ``{layer: [channels]}``. As the
    server groups them (PROTOCOL.md, "Passes"): a channel's layer is its name before the last
    dot; in a multi-part file the part's name comes first unless the channel's already starts
    with it."""
    if data[:4] != b"\x76\x2f\x31\x01":
        raise WorkerError("Blender did not write an OpenEXR file")
    multipart = bool(struct.unpack_from("<I", data, 4)[0] & 0x1000)
    pos = 8

    def cstr(at):
        end = data.index(b"\0", at)
        return data[at:end].decode("utf-8", "replace"), end + 1

    layers = {}
    while data[pos] != 0:
        attrs = {}
        while data[pos] != 0:
            name, pos = cstr(pos)
            _, pos = cstr(pos)
            (size,) = struct.unpack_from("<i", data, pos)
            attrs[name] = data[pos + 4:pos + 4 + size]
            pos += 4 + size
        pos += 1
        part = attrs["name"].rstrip(b"\0").decode("utf-8", "replace") if "name" in attrs else ""
        chlist, at = attrs.get("channels", b"\0"), 0
        while chlist[at] != 0:
            end = chlist.index(b"\0", at)
            channel = chlist[at:end].decode("utf-8", "replace")
            at = end + 1 + 16  # pixel type, pLinear and reserved, x and y sampling
            if multipart and part and not channel.startswith(part + "."):
                channel = f"{part}.{channel}"
            prefix, _, short = channel.rpartition(".")
            layers.setdefault(prefix, []).append(short)
        if not multipart:
            break
    return layers


def check_layers(exr, beauty, aovs):
    """Every layer the frame expects is in the pass Blender wrote, with its channels."""
    have = exr_layers(exr)
    wanted = [(beauty, ["R", "G", "B"])] + list(aovs)
    for name, channels in wanted:
        if not set(channels) <= set(have.get(name, [])):
            listing = "; ".join(f"{n or '(unnamed)'}: {','.join(c)}" for n, c in sorted(have.items()))
            raise WorkerError(f"the pass Blender wrote has no layer {name} with channels "
                              f"{','.join(channels)}; its layers are {listing}")


def render(scene, path, layer):
    """Renders view layer `layer` of the scene to `path`; returns the file's bytes."""
    scene.render.filepath = path
    bpy.ops.render.render(write_still=True, layer=layer)
    try:
        with open(path, "rb") as f:
            return f.read()
    except OSError as e:
        raise WorkerError(f"Blender wrote no pass to {path}: {e}") from None


def convergence(client, frame):
    """The server's convergence figures of the frame, with its verdict (None while it has none)."""
    try:
        return client.frame_info(frame).get("convergence")
    except sc.SplatdError as e:
        if e.status == 403:
            raise WorkerError("--until-converged reads the frame's convergence, which needs a "
                              f"token with the read role as well as write (roles read,write): {e}")
        raise


def converged(figures):
    """Whether the server's verdict is that the frame has converged."""
    return bool(figures and figures.get("converged"))


def not_converged_because(figures):
    """Why the frame has not converged, from what the server says it waits on (PROTOCOL.md)."""
    if not figures:
        return "the server has no figures of it yet"
    below = figures["converged_below"]
    return {
        "pixels_without_samples": "some pixels have no samples",
        "removed_energy": f"the resolve removes {figures['removed_fraction']:.2%} of its energy, "
                          f"more than {below:.2%}",
        "own_samples": f"{figures['deficit_fraction']:.2%} of its energy is in bands short of "
                       f"each pixel's own samples, more than {below:.2%}",
    }.get(figures.get("waiting_on"), "the server does not say why")


def main(argv):
    args = parse_args(worker_argv(argv))
    scene = open_scene(args)
    configure(scene, args.resolution, args.spp)
    width, height = scene.render.resolution_x, scene.render.resolution_y
    camera = scene.camera
    if camera is None:
        raise WorkerError(f"scene {scene.name!r} has no camera")
    view_layer = bpy.context.view_layer.name

    if args.reference:
        scene.cycles.samples = args.reference
        scene.cycles.pixel_filter_type = "BOX"
        scene.cycles.filter_width = 1.0
        scene.cycles.seed = args.seed
        render(scene, os.path.abspath(args.output), view_layer)
        print(f"reference: {width}x{height} at {args.reference} spp -> {args.output}")
        return

    frame = args.frame or scene.name
    try:
        sc.validate_frame_id(frame)
    except sc.WireError as e:
        raise WorkerError(f"the scene's name {scene.name!r} is no frame id ({e}); give --frame")
    worker = args.worker if args.worker is not None else default_worker(
        args.seed, args.job_index, args.job_count)
    count = job_share(args.passes, args.job_index, args.job_count)
    passes = range(args.first_pass, args.first_pass + count)
    beauty, aovs = enable_aovs(scene, args.aovs) if args.aovs else (None, [])

    # A near-point pixel filter: each pass samples one position per pixel, moved below.
    scene.cycles.pixel_filter_type = "BOX"
    scene.cycles.filter_width = 0.01
    # Camera shift is in units of the larger image side; one pixel is 1 / max(W, H).
    base_x, base_y = camera.data.shift_x, camera.data.shift_y
    per_pixel = 1.0 / max(width, height)
    client = sc.Client(args.url, token=args.token)
    # Before any rendering, so that a frame of another size or other AOVs stops the job at once.
    client.create_or_get(frame, width, height, aovs=aovs or None)
    outbox = client.outbox(frame, worker)
    share = f"passes {passes.start}..{passes.stop - 1}" if count else "no passes (a smaller budget)"
    print(f"worker {worker}: job {args.job_index} of {args.job_count}, {share} of frame {frame} "
          f"({width}x{height}{', AOVs ' + ', '.join(n for n, _ in aovs) if aovs else ''}) "
          f"at {args.url}", flush=True)
    keep = os.path.abspath(args.keep_dir) if args.keep_dir else tempfile.mkdtemp(prefix="splatd-blender-")
    os.makedirs(keep, exist_ok=True)
    rendered = duplicates = 0
    # The verdict on the frame after the latest pass posted, asked for while the next renders
    # (over a connection of its own).
    judge = sc.Client(args.url, token=args.token) if args.until_converged else None
    asking = concurrent.futures.ThreadPoolExecutor(max_workers=1) if judge else None
    verdict = None
    try:
        if judge and converged(convergence(judge, frame)):
            print(f"frame {frame} has converged", flush=True)
            passes = range(0)
        for k in passes:
            seed, dx, dy = pass_seeds(worker, k)
            scene.cycles.seed = seed
            camera.data.shift_x = base_x + dx * per_pixel
            # Image rows go down, the camera's y up: a shift of +dy pixels downwards is -dy.
            camera.data.shift_y = base_y - dy * per_pixel
            path = os.path.join(keep, f"pass_{k}.exr")
            exr = render(scene, path, view_layer)
            if not args.keep_dir:
                os.remove(path)
            if verdict is not None and converged(verdict.result()):
                print(f"frame {frame} has converged (with the passes posted before pass {k}, "
                      f"which was rendered meanwhile and is not posted)", flush=True)
                verdict = None
                break
            if rendered == 0 and aovs:
                check_layers(exr, beauty, aovs)
            ack = outbox.post_pass(k, exr, layer=beauty)
            rendered += 1
            duplicates += bool(ack["duplicate"])
            print(f"pass {k}: seed {seed}, shift ({dx:+.3f}, {dy:+.3f}) px, {ack['accepted']} "
                  f"samples{' (already there)' if ack['duplicate'] else ''}", flush=True)
            if asking:
                verdict = asking.submit(convergence, judge, frame)
        if verdict is not None:
            figures = verdict.result()
            print(f"frame {frame}: {count} passes rendered, the budget, and " + (
                  "it has converged" if converged(figures)
                  else f"it has not converged: {not_converged_because(figures)}"), flush=True)
    finally:
        if asking:
            asking.shutdown(wait=True, cancel_futures=True)
        camera.data.shift_x, camera.data.shift_y = base_x, base_y
        if not args.keep_dir:
            shutil.rmtree(keep, ignore_errors=True)
    durable = outbox.sync()["durable"]
    resent = outbox.resent
    where = "on the server's disk" if durable else "applied (the server keeps frames in memory only)"
    print(f"worker {worker}: {rendered} passes posted, {where}"
          f"{f'; {resent} resent after a server restart' if resent else ''}", flush=True)
    if duplicates:
        print(f"warning: {duplicates} of {rendered} passes were already in frame {frame} under "
              f"worker {worker}: an earlier run, or another process with the same --seed, "
              "--job-index and --job-count, rendered them (counted once); give each machine its "
              "own --job-index", file=sys.stderr, flush=True)


def run():
    try:
        main(sys.argv)
    except WorkerError as e:
        sys.exit(f"blender_worker.py: error: {e}")
    except sc.SplatdError as e:
        said = "the server refused" if e.status else "no answer from the server"
        sys.exit(f"blender_worker.py: {said}: {e}")
    except (sc.WireError, OSError) as e:
        sys.exit(f"blender_worker.py: error: {e}")
    except Exception:  # noqa: BLE001 - Blender's --python exits 0 after a traceback: not here
        traceback.print_exc()
        sys.exit("blender_worker.py: failed (above)")


if __name__ == "__main__":
    run()

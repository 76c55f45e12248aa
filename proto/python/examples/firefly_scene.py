"""Builds a small Cycles scene full of fireflies, for the README's before/after picture.

Run by the worker before it renders (with Blender or the bpy module):

    blender -b --factory-startup --python ../blender_worker.py -- --scene-script firefly_scene.py ...

A diffuse room lit by one tiny, very bright lamp, with a mirror sphere and a glass sphere beside
it. Light from the lamp that bounces off the mirror or through the glass onto the diffuse floor
and wall (a caustic) can only be found by a path that bounces off the floor in exactly the right
direction: at a few samples per pixel most pixels miss it and the few that hit it are thousands
of times too bright, the fireflies path tracers are known for.
"""

import math

import bpy


def material(name, build):
    mat = bpy.data.materials.new(name)
    if bpy.app.version < (5, 0, 0):  # always on from Blender 5
        mat.use_nodes = True
    nodes = mat.node_tree.nodes
    nodes.remove(nodes["Principled BSDF"])
    shader = build(nodes)
    mat.node_tree.links.new(shader.outputs[0], nodes["Material Output"].inputs["Surface"])
    return mat


def diffuse(rgb):
    def build(nodes):
        node = nodes.new("ShaderNodeBsdfDiffuse")
        node.inputs["Color"].default_value = (*rgb, 1.0)
        return node
    return build


def mirror(nodes):
    node = nodes.new("ShaderNodeBsdfGlossy")
    node.inputs["Color"].default_value = (0.95, 0.9, 0.8, 1.0)
    node.inputs["Roughness"].default_value = 0.02
    return node


def glass(nodes):
    node = nodes.new("ShaderNodeBsdfGlass")
    node.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    node.inputs["Roughness"].default_value = 0.0
    node.inputs["IOR"].default_value = 1.5
    return node


def lamp(nodes):
    node = nodes.new("ShaderNodeEmission")
    node.inputs["Color"].default_value = (1.0, 0.85, 0.6, 1.0)
    node.inputs["Strength"].default_value = 3000.0
    return node


def add(obj_op, mat, **kwargs):
    obj_op(**kwargs)
    bpy.context.object.data.materials.append(mat)
    return bpy.context.object


def build(scene):
    for obj in list(bpy.data.objects):
        bpy.data.objects.remove(obj, do_unlink=True)
    world = scene.world or bpy.data.worlds.new("fireflies")
    scene.world = world
    if bpy.app.version < (5, 0, 0):
        world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.02

    add(bpy.ops.mesh.primitive_plane_add, material("floor", diffuse((0.8, 0.8, 0.8))),
        size=12.0, location=(0.0, 0.0, 0.0))
    add(bpy.ops.mesh.primitive_plane_add, material("wall", diffuse((0.7, 0.45, 0.3))),
        size=12.0, location=(0.0, 2.5, 3.0), rotation=(math.pi / 2, 0.0, 0.0))
    add(bpy.ops.mesh.primitive_plane_add, material("side", diffuse((0.3, 0.5, 0.7))),
        size=12.0, location=(-3.0, 0.0, 3.0), rotation=(0.0, math.pi / 2, 0.0))
    add(bpy.ops.mesh.primitive_uv_sphere_add, material("mirror", mirror),
        radius=0.7, location=(-0.9, 0.8, 0.7), segments=64, ring_count=32)
    bpy.ops.object.shade_smooth()
    add(bpy.ops.mesh.primitive_uv_sphere_add, material("glass", glass),
        radius=0.55, location=(0.9, 0.2, 0.55), segments=64, ring_count=32)
    bpy.ops.object.shade_smooth()
    # The lamp: a sphere 4 cm across, up and behind the spheres.
    add(bpy.ops.mesh.primitive_uv_sphere_add, material("lamp", lamp),
        radius=0.02, location=(0.2, 1.6, 2.4))

    cam = bpy.data.cameras.new("camera")
    cam.lens = 32.0
    cam_obj = bpy.data.objects.new("camera", cam)
    cam_obj.location = (0.0, -5.0, 1.6)
    cam_obj.rotation_euler = (math.radians(80.0), 0.0, 0.0)
    scene.collection.objects.link(cam_obj)
    scene.camera = cam_obj
    scene.render.resolution_x, scene.render.resolution_y = 192, 128
    # Paths long enough for light to reach the floor through both faces of the glass.
    c = scene.cycles
    c.max_bounces = 8
    c.diffuse_bounces = 4
    c.glossy_bounces = 4
    c.transmission_bounces = 8
    c.caustics_reflective = True
    c.caustics_refractive = True
    c.blur_glossy = 0.0


build(bpy.context.scene)

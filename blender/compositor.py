"""The compositor set-up for F12: the DVR image laid over the Render Layers, and its check.

:func:`setup_compositor` lays the DVR image over the Render Layers image (Alpha Over,
premultiplied) in the scene's compositor, so F12 renders and animations include it. Works on
the 4.x compositor (``scene.use_nodes``, ``scene.node_tree``, Composite node) and the 5.x one
(``scene.compositing_node_group``: a CompositorNodeTree with an Image output socket and a Group
Output node).

Caveat: the compositor lays the DVR image as it was last rendered. Render it (Render VolumeEVM)
with the same camera, frame and resolution before F12; the volume's rays stop at the depth of
the scene as it was then (the scene cannot be rendered again from inside its own render, so F12
alone cannot make a depth-correct DVR of a changed scene). A stale DVR (rendered for another
frame, camera or resolution, :func:`stale_dvr`) is never laid over a render silently: the
Render panel says so, and the ``render_pre`` handler :func:`check_view` mutes the Alpha Over node
for that render (F12 gives the scene without the volume) and says why, as an error on stderr
under ``--background``; once the DVR matches the view again the node is unmuted. The Render
setting Allow Stale DVR (``allow_stale_dvr``) lays it anyway, with a warning. For animations,
:func:`.dvr.render_dvr_animation` renders scene pass, DVR and composite frame by frame.
"""

import sys

import bpy

from .dvr import VIEW_KEY, view_signature

#: Node names of the compositor set-up (found again, never duplicated).
NODE_IMAGE = "VolumeEVM DVR"
NODE_OVER = "VolumeEVM Over"
#: Custom property of the Alpha Over node while :func:`check_view` keeps it muted.
MUTED_KEY = "volumeevm_stale"


def over_sockets(node):
    """(background, foreground) inputs of an Alpha Over node (5.x names them; 4.x does not)."""
    if "Background" in node.inputs:
        return node.inputs["Background"], node.inputs["Foreground"]
    return node.inputs[1], node.inputs[2]


def _node(tree, name, kind):
    node = tree.nodes.get(name)
    if node is None or node.bl_idname != kind:
        node = tree.nodes.new(kind)
        node.name = node.label = name
    return node


def _first(tree, kind):
    return next((n for n in tree.nodes if n.bl_idname == kind), None)


def setup_compositor(scene, image):
    """Lay ``image`` (premultiplied) over the render in ``scene``'s compositor.

    Whatever fed the compositor's output stays as the background (the Render Layers image in a
    new set-up); running it again only points the Image node at ``image``.

    Parameters
    ----------
    scene : bpy.types.Scene
    image : bpy.types.Image
        The DVR alone (``dvr.DEFAULT_IMAGE + " DVR"``), premultiplied.

    Returns
    -------
    bpy.types.NodeTree
        The compositing tree (5.x: ``scene.compositing_node_group``; 4.x: ``scene.node_tree``).
    """
    if hasattr(scene, "compositing_node_group"):  # Blender 5.x
        tree = scene.compositing_node_group
        if tree is None:
            tree = bpy.data.node_groups.new("VolumeEVM Compositing", "CompositorNodeTree")
            scene.compositing_node_group = tree
        if not any(item.item_type == "SOCKET" and item.in_out == "OUTPUT"
                   for item in tree.interface.items_tree):
            tree.interface.new_socket("Image", in_out="OUTPUT", socket_type="NodeSocketColor")
        output = _first(tree, "NodeGroupOutput") or tree.nodes.new("NodeGroupOutput")
        target = output.inputs[0]
    else:  # Blender 4.x
        scene.use_nodes = True
        tree = scene.node_tree
        output = _first(tree, "CompositorNodeComposite") or tree.nodes.new(
            "CompositorNodeComposite")
        target = output.inputs["Image"]
    scene.render.use_compositing = True
    layers = _first(tree, "CompositorNodeRLayers")
    if layers is None:
        layers = tree.nodes.new("CompositorNodeRLayers")
        layers.location = (output.location.x - 600, output.location.y)
    image_node = _node(tree, NODE_IMAGE, "CompositorNodeImage")
    image_node.image = image
    over = _node(tree, NODE_OVER, "CompositorNodeAlphaOver")
    over.location = (output.location.x - 220, output.location.y)
    image_node.location = (over.location.x - 260, over.location.y - 220)
    background, foreground = over_sockets(over)
    feeding = target.links[0].from_socket if target.is_linked else None
    if feeding is not None and feeding.node != over:
        tree.links.new(feeding, background)
    elif not background.is_linked:
        tree.links.new(layers.outputs["Image"], background)
    tree.links.new(image_node.outputs["Image"], foreground)
    tree.links.new(over.outputs[0], target)
    return tree


def _compositor_nodes(scene):
    """The (Image, Alpha Over) nodes of the scene's VolumeEVM compositor set-up, or None."""
    tree = getattr(scene, "compositing_node_group", None)
    if tree is None and not hasattr(scene, "compositing_node_group"):
        tree = scene.node_tree if scene.use_nodes else None
    if tree is None:
        return None
    image_node, over = tree.nodes.get(NODE_IMAGE), tree.nodes.get(NODE_OVER)
    if image_node is None or over is None or image_node.image is None or image_node.mute:
        return None
    if over.mute and not over.get(MUTED_KEY):  # muted by the user: the DVR is not used
        return None
    return image_node, over


def stale_dvr(scene):
    """What is wrong when F12 would lay a DVR image rendered for another view (frame, camera,
    resolution: :func:`.dvr.view_signature`) over ``scene``'s render; "" when nothing is."""
    nodes = _compositor_nodes(scene)
    if nodes is None or not scene.render.use_compositing:
        return ""
    image = nodes[0].image
    stored = image.get(VIEW_KEY)
    now = view_signature(scene)
    if stored == now:
        return ""
    if stored is None:
        return f"{image.name!r} has not been rendered by Render VolumeEVM"
    then, this = stored.split("; ")[0], now.split("; ")[0]
    where = f" ({then}; this render: {this})" if then != this else ""
    return f"{image.name!r} was rendered for another frame, camera or resolution{where}"


@bpy.app.handlers.persistent
def check_view(scene, *_args):
    """render_pre: mute the Alpha Over node while the DVR image is stale (:func:`stale_dvr`),
    unless the Render settings allow a stale DVR; unmute it once the DVR matches again."""
    nodes = _compositor_nodes(scene)
    if nodes is None:
        return
    over = nodes[1]
    problem = stale_dvr(scene)
    allowed = scene.volumeevm_render.allow_stale_dvr
    if over.get(MUTED_KEY) and (allowed or not problem):
        over.mute = False
        del over[MUTED_KEY]
    if not problem:
        return
    if allowed:
        print(f"[volumeevm] warning: {problem}; laid over the render as it is (Allow Stale DVR)",
              flush=True)
        return
    over.mute = True
    over[MUTED_KEY] = True
    message = (f"{problem}: this render leaves it out. Run Render VolumeEVM again (or Render "
               f"VolumeEVM Animation), or turn on Allow Stale DVR")
    if bpy.app.background:
        print(f"[volumeevm] error: {message}", file=sys.stderr, flush=True)
    else:
        print(f"[volumeevm] warning: {message}", flush=True)


HANDLERS = (("render_pre", check_view),)

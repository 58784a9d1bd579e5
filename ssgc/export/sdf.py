"""SDFormat 1.9: one `<world>` with one `<model>` per object (Drake's Parser, Gazebo).

Each model has one link, `body`, with the type's inertia, its visual geometry and its collision
geometry (primitives as themselves, a tray as its five boxes; a mesh's convex pieces as OBJ
files, marked `drake:declare_convex` so Drake uses them as convex shapes).  Fixed objects are
`<static>`.
"""

from __future__ import annotations

from xml.sax.saxutils import escape, quoteattr

import numpy as np

from ssgc.assets import Shape
from ssgc.export.bodies import Body, SceneBodies, collision_piece, mesh_files, num
from ssgc.geometry import quat_to_rpy

SUFFIX = ".sdf"
DRAKE_NS = "http://drake.mit.edu"
# How every main file begins (a dmd model file, also SDFormat, has no <world>)
MAIN_START = (
    f'<?xml version="1.0"?>\n<sdf version="1.9" xmlns:drake="{DRAKE_NS}">\n  <world '.encode()
)


def pose_text(xyz: np.ndarray, quat: np.ndarray) -> str:
    return " ".join(num(v) for v in (*xyz, *quat_to_rpy(quat)))


def geometry_xml(shape: Shape, mesh_uri: str, convex: bool = False) -> str:
    """The `<geometry>` content.  `convex`: a convex piece, marked `<drake:declare_convex/>`
    inside its `<mesh>`, the one place Drake accepts it (after `</geometry>`, Drake's parser
    refused the whole file as soon as the plant had a SceneGraph)."""
    if shape.kind == "box":
        return f"<box><size>{' '.join(num(v) for v in shape.size)}</size></box>"
    if shape.kind == "cylinder":
        r, h = shape.size
        return f"<cylinder><radius>{num(r)}</radius><length>{num(h)}</length></cylinder>"
    if shape.kind == "sphere":
        return f"<sphere><radius>{num(shape.size[0])}</radius></sphere>"
    mark = "<drake:declare_convex/>" if convex else ""
    return f"<mesh><uri>{escape(mesh_uri)}</uri>{mark}</mesh>"


def link_xml(shape: Shape | None, meshes: str, indent: str = "      ") -> str:
    """The link `body` of a type; mesh files are looked for under the folder `meshes`."""
    if shape is None:
        return f'{indent}<link name="body"/>'
    i = shape.inertia
    # a primitive is centred on the geometry's origin; a mesh's OBJ files are already placed
    placed = (
        f"<pose>{' '.join(num(v) for v in shape.origin)} 0 0 0</pose>"
        if shape.primitive and any(shape.origin)
        else ""
    )
    lines = [
        f'{indent}<link name="body">',
        f"{indent}  <inertial>",
        f"{indent}    <pose>{' '.join(num(v) for v in shape.com)} 0 0 0</pose>",
        f"{indent}    <mass>{num(shape.mass)}</mass>",
        f"{indent}    <inertia><ixx>{num(i[0, 0])}</ixx><ixy>{num(i[0, 1])}</ixy>"
        f"<ixz>{num(i[0, 2])}</ixz><iyy>{num(i[1, 1])}</iyy><iyz>{num(i[1, 2])}</iyz>"
        f"<izz>{num(i[2, 2])}</izz></inertia>",
        f"{indent}  </inertial>",
        f'{indent}  <visual name="visual">{placed}<geometry>'
        f"{geometry_xml(shape, f'{meshes}/{shape.type}.obj')}</geometry></visual>",
    ]
    if shape.primitive:
        lines.append(
            f'{indent}  <collision name="collision">{placed}<geometry>'
            f"{geometry_xml(shape, '')}</geometry></collision>"
        )
    for k in range(len(shape.collision)):
        uri = f"{meshes}/{collision_piece(shape.type, k)}.obj"
        lines.append(
            f'{indent}  <collision name="collision_{k}"><geometry>'
            f"{geometry_xml(shape, uri, convex=True)}</geometry></collision>"
        )
    for k, (centre, sides) in enumerate(shape.boxes):  # a tray's, each placed in the frame
        lines.append(
            f'{indent}  <collision name="collision_{k}"><pose>{" ".join(map(num, centre))} 0 0 0'
            f"</pose><geometry><box><size>{' '.join(map(num, sides))}</size></box></geometry>"
            "</collision>"
        )
    lines.append(f"{indent}</link>")
    return "\n".join(lines)


def model_xml(body: Body, meshes: str) -> str:
    return "\n".join(
        [
            f"    <model name={quoteattr(body.name)}>",
            f"      <static>{'true' if body.fixed else 'false'}</static>",
            f"      <pose>{pose_text(body.xyz, body.quat)}</pose>",
            link_xml(body.shape, meshes),
            "    </model>",
        ]
    )


def world_name(name: str) -> str:
    """The scene's name, unless SDFormat reserves it (`world`, and any `__x__`), as a scene
    name may be: then `NAME_scene`, which it does not."""
    reserved = name == "world" or (name.startswith("__") and name.endswith("__"))
    return f"{name}_scene" if reserved else name


def files(scene: SceneBodies) -> dict[str, str | bytes]:
    """`NAME.sdf` and the OBJ files it names, relative to the output directory."""
    meshes = "meshes"  # shared by every scene exported to the same directory
    text = "\n".join(
        [
            '<?xml version="1.0"?>',
            f'<sdf version="1.9" xmlns:drake="{DRAKE_NS}">',
            f"  <world name={quoteattr(world_name(scene.name))}>",
            *(model_xml(b, meshes) for b in scene.bodies),
            "  </world>",
            "</sdf>",
            "",
        ]
    )
    return {f"{scene.name}{SUFFIX}": text, **mesh_files(scene, meshes, collision=True)}

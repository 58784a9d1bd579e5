"""MJCF for MuJoCo: one `<body>` per object, a `<freejoint>` on each free one.

Every body carries its type's `<inertial>` (MuJoCo does not recompute it: `inertiafromgeom`
is off), a visual geom (group 1, no contacts) and its collision geoms (group 3): primitives
as themselves, a tray as its five boxes, a mesh's convex pieces as mesh assets written inline
(a revolve has hundreds: one OBJ file each made `ssg settle` write them all for every scene).
Fixed bodies have no joint, so they are welded to the world.  `floor=True` adds a ground plane
at z = 0 (for settling).
"""

from __future__ import annotations

from xml.sax.saxutils import quoteattr

import numpy as np

from ssgc.assets import Shape
from ssgc.errors import SsgError
from ssgc.export.bodies import (
    Body,
    SceneBodies,
    collision_piece,
    mesh_files,
    num,
    principal_axes,
    used_shapes,
)
from ssgc.geometry import matrix_to_quat

SUFFIX = ".xml"
MAIN_START = b"<mujoco model="  # how every main file begins
# Stiff, critically damped contacts: objects at rest sink less than 1 mm into each other.
CONTACT = 'solref="0.004 1" solimp="0.95 0.99 0.0005"'


def _nums(values: object) -> str:
    return " ".join(num(v) for v in np.ravel(values))


def _primitive(shape: Shape) -> str:
    if shape.kind == "box":
        return f'type="box" size="{_nums(np.asarray(shape.size) / 2)}"'
    if shape.kind == "cylinder":
        return f'type="cylinder" size="{_nums([shape.size[0], shape.size[1] / 2])}"'
    return f'type="sphere" size="{_nums(shape.size)}"'


def _geoms(shape: Shape) -> list[str]:
    if shape.primitive:  # centred on the geometry's origin (a mesh's OBJ is placed)
        pos = f'pos="{_nums(shape.origin)}" ' if any(shape.origin) else ""
        geom = f"{_primitive(shape)} {pos}"
        return [  # group 3 alone is hidden by MuJoCo's viewer, which shows groups 0-2
            f'<geom name="{{}}_visual" {geom}group="1" contype="0" conaffinity="0"/>',
            f'<geom name="{{}}_geom" {geom}group="3" {CONTACT}/>',
        ]
    out = [
        f'<geom name="{{}}_visual" type="mesh" mesh="{shape.type}" group="1" '
        'contype="0" conaffinity="0"/>'
    ]
    out += [
        f'<geom name="{{}}_collision_{k}" type="mesh" mesh="{collision_piece(shape.type, k)}" '
        f'group="3" {CONTACT}/>'
        for k in range(len(shape.collision))
    ]
    out += [  # a tray's boxes, each placed in the frame
        f'<geom name="{{}}_collision_{k}" type="box" size="{_nums(np.asarray(sides) / 2)}" '
        f'pos="{_nums(centre)}" group="3" {CONTACT}/>'
        for k, (centre, sides) in enumerate(shape.boxes)
    ]
    return out


def _triangle_inequality(moments: np.ndarray) -> np.ndarray:
    """Principal moments (ascending) with the largest at most the sum of the other two.

    For a flat body (a box 1e-9 m thick) the largest equals that sum, and rounding put it one
    float step above: MuJoCo refused the file ("A + B >= C").  Lowering it by that step is
    exact to 1e-16; MuJoCo's `balanceinertia` instead sets all three to their mean, 21% to
    330% off for a 0.3 x 0.7 m sheet."""
    out = np.array(moments, dtype=float)
    out[2] = min(out[2], out[0] + out[1])
    return out


def _inertial(shape: Shape) -> str:
    moments, axes = principal_axes(shape.inertia)
    moments = _triangle_inequality(moments)
    return (
        f'<inertial pos="{_nums(shape.com)}" quat="{_nums(matrix_to_quat(axes))}" '
        f'mass="{num(shape.mass)}" diaginertia="{_nums(moments)}"/>'
    )


def body_xml(body: Body) -> str:
    name = quoteattr(body.name)
    lines = [f'    <body name={name} pos="{_nums(body.xyz)}" quat="{_nums(body.quat)}">']
    if not body.fixed:
        lines.append(f"      <freejoint name={name}/>")
    if body.shape is not None:
        lines.append(f"      {_inertial(body.shape)}")
        lines += [f"      {g.format(body.name)}" for g in _geoms(body.shape)]
    lines.append("    </body>")
    return "\n".join(lines)


def _mesh_asset(name: str, piece: object | None = None) -> str:
    """A mesh asset whose own inertia is a shell's: MuJoCo computes every mesh's inertia even
    though none is used (`inertiafromgeom` is off), and refuses a mesh that encloses almost no
    volume (two crossed flat quads, which validation accepts: their hull has one), while a
    shell needs only an area.  MuJoCo places the geom by the mesh's own frame either way.
    The visual surface is its OBJ file; a convex `piece` (trimesh) is written inline."""
    if piece is None:
        return f'    <mesh name="{name}" file="{name}.obj" inertia="shell"/>'
    faces = " ".join(str(int(i)) for i in np.ravel(piece.faces))  # type: ignore[attr-defined]
    return (
        f'    <mesh name="{name}" vertex="{_nums(piece.vertices)}" face="{faces}" '  # type: ignore[attr-defined]
        'inertia="shell"/>'
    )


MUJOCO_MINVAL = 1e-15  # mjMINVAL: MuJoCo counts a triangle whose |cross product| is below it as 0


def _mujoco_area(mesh: object) -> float:
    """A mesh's surface area as MuJoCo measures it: triangles with |(b - a) x (c - a)| below
    `MUJOCO_MINVAL` count as none, so a teacup scaled by 1e-6 (edges of 1e-8 m) has none."""
    v = np.asarray(mesh.vertices, dtype=float)[np.asarray(mesh.faces)]  # type: ignore[attr-defined]
    cross = np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    return float(0.5 * np.sum(cross[cross >= MUJOCO_MINVAL]))


def refuse_meshes_too_small(scene: SceneBodies) -> None:
    """Refuse, naming every type at fault, meshes MuJoCo refuses to load ("mesh surface area is
    too small"): their triangles are each below its smallest area, whatever their sum."""
    small = [
        shape.type
        for shape in used_shapes(scene)
        if not shape.primitive
        and any(_mujoco_area(m) < MUJOCO_MINVAL for m in (shape.mesh, *shape.collision))
    ]
    if small:
        raise SsgError.single(
            f"type(s) {', '.join(repr(s) for s in small)}: a mesh too small for MuJoCo, whose "
            f"triangles are each below the {MUJOCO_MINVAL:g} its area counts (edges of about "
            "3e-8 m); scale the mesh up, or use a primitive for so small a thing"
        )


def mjcf_text(
    scene: SceneBodies, meshdir: str = "meshes", floor: bool = False, timestep: float = 0.001
) -> str:
    refuse_meshes_too_small(scene)
    assets = []
    for shape in used_shapes(scene):
        if not shape.primitive:
            assets.append(_mesh_asset(shape.type))
            assets += [
                _mesh_asset(collision_piece(shape.type, k), piece)
                for k, piece in enumerate(shape.collision)
            ]
    ground = [f'    <geom name="floor" type="plane" size="0 0 1" {CONTACT}/>'] if floor else []
    return "\n".join(
        [
            f"<mujoco model={quoteattr(scene.name)}>",
            # MuJoCo refuses a moving body's mass or inertia below 1e-15 (a 0.1 mm grain, a
            # density of 1e-300): such bodies are raised to these floors instead
            f'  <compiler angle="radian" meshdir={quoteattr(meshdir)} inertiafromgeom="false" '
            'boundmass="1e-12" boundinertia="1e-14"/>',
            # multiccd: several contact points between flat faces (a tray on a tray), not one
            f'  <option timestep="{timestep!r}"><flag multiccd="enable"/></option>',
            *(["  <asset>", *assets, "  </asset>"] if assets else []),
            "  <worldbody>",
            *ground,
            *(body_xml(b) for b in scene.bodies),
            "  </worldbody>",
            "</mujoco>",
            "",
        ]
    )


def files(scene: SceneBodies) -> dict[str, str | bytes]:
    """`NAME.xml` and the OBJ files of its visual meshes (in `meshes/`)."""
    return {f"{scene.name}{SUFFIX}": mjcf_text(scene), **mesh_files(scene, "meshes")}

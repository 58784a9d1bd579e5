"""Drake model directives (`.dmd.yaml`) and the SDFormat model files they name.

Every type becomes one model file, `models/TYPE.sdf` (its link `body`); every object one
`add_model` named by its id.  Free objects get `default_free_body_pose`; fixed ones an
`add_weld` from the world.  The files are found through the package `ssgc_export`, whose
`package.xml` is written in the output directory:

    parser = Parser(plant); parser.package_map().AddPackageXml("OUT/package.xml")
    ProcessModelDirectives(LoadModelDirectives("OUT/NAME.dmd.yaml"), plant, parser)
"""

from __future__ import annotations

import json

import numpy as np

from ssgc.export.bodies import Body, SceneBodies, flushed, mesh_files, used_shapes
from ssgc.export.sdf import DRAKE_NS, link_xml
from ssgc.geometry import quat_to_rpy

SUFFIX = ".dmd.yaml"
MAIN_START = b"# Drake model directives of scene "  # how every main file begins
PACKAGE = "ssgc_export"
# The model of an object without geometry: a name no type can have (type names have no "-").
EMPTY = "no-geometry"
PACKAGE_XML = f"""<?xml version="1.0"?>
<package format="2">
  <name>{PACKAGE}</name>
  <version>0.0.0</version>
  <description>Scenes exported by ssgc (ssg export --format dmd).</description>
  <maintainer email="nobody@example.com">ssgc</maintainer>
  <license>MIT</license>
</package>
"""


def _list(values: np.ndarray) -> str:
    return json.dumps([flushed(v) for v in values])


def _transform(xyz: np.ndarray, quat: np.ndarray) -> str:
    rpy_deg = np.degrees(quat_to_rpy(quat))
    return f"{{translation: {_list(xyz)}, rotation: !Rpy {{deg: {_list(rpy_deg)}}}}}"


def _directives(body: Body) -> list[str]:
    model = f"package://{PACKAGE}/models/{body.type}.sdf"
    if body.shape is None:
        model = f"package://{PACKAGE}/models/{EMPTY}.sdf"
    out = [f"- add_model:\n    name: {body.name}\n    file: {model}"]
    if body.fixed:
        out.append(
            f"- add_weld:\n    parent: world\n    child: {body.name}::body\n"
            f"    X_PC: {_transform(body.xyz, body.quat)}"
        )
    else:
        out[0] += (
            "\n    default_free_body_pose:\n"
            f"      body: {{base_frame: world, {_transform(body.xyz, body.quat)[1:-1]}}}"
        )
    return out


def _model_file(name: str, link: str) -> str:
    """A type's model.  `add_model` names each instance, so the name inside only has to be a
    name SDFormat accepts: `world` and `__x__` are reserved, and a type may be called that."""
    name = f"{name}_model"
    return (
        f'<?xml version="1.0"?>\n<sdf version="1.9" xmlns:drake="{DRAKE_NS}">\n'
        f'  <model name="{name}">\n{link}\n  </model>\n</sdf>\n'
    )


def files(scene: SceneBodies) -> dict[str, str | bytes]:
    """`NAME.dmd.yaml`, `package.xml`, `models/TYPE.sdf` and the meshes they name."""
    lines = [f"# Drake model directives of scene '{scene.name}' (grammar '{scene.grammar}')"]
    lines += ["directives:" if scene.bodies else "directives: []"]  # a bare key is null
    for body in scene.bodies:
        lines += _directives(body)
    out: dict[str, str | bytes] = {
        f"{scene.name}{SUFFIX}": "\n".join(lines) + "\n",
        "package.xml": PACKAGE_XML,
    }
    for shape in used_shapes(scene):
        out[f"models/{shape.type}.sdf"] = _model_file(shape.type, link_xml(shape, "meshes", "    "))
    if any(b.shape is None for b in scene.bodies):
        out[f"models/{EMPTY}.sdf"] = _model_file("empty", link_xml(None, "meshes", "    "))
    out.update(mesh_files(scene, "models/meshes", collision=True))
    return out

"""USD (text, `.usda`) through usd-core's `pxr`: one Xform per object under `/World`.

Each Xform, named by the object's id, has its pose as a translate and an orient op and holds
its geometry as a prim (`Cube` scaled to the box, `Cylinder`, `Sphere`, or a `Mesh` with the
mesh's triangles).  UsdPhysics carries the rest: free objects are rigid bodies with their
mass, centre of mass and principal inertia; geometry is a collider (a mesh's as its convex
hull or convex decomposition); fixed objects are colliders without a rigid body (static).  A
revolve's exact convex pieces (`Shape.exact_pieces`) are colliders of their own, `Mesh`es
under `ID/collision` with purpose `guide` (not drawn), and its visual mesh collides with
nothing: a simulator's own decomposition of the surface would be approximate.  A tray is drawn
as its mesh and collides as its five boxes, `Cube`s under `ID/collision` likewise.
"""

from __future__ import annotations

import numpy as np

from ssgc.assets import Shape
from ssgc.export.bodies import Body, SceneBodies, principal_axes
from ssgc.geometry import matrix_to_quat

SUFFIX = ".usda"
MAIN_START = b"#usda "  # how every main file begins


def require() -> None:
    """Refuse the format before any work when usd-core is not installed."""
    _pxr()


def _pxr():  # type: ignore[no-untyped-def]
    try:
        from pxr import Gf, Usd, UsdGeom, UsdPhysics
    except ImportError:
        from ssgc.errors import SsgError

        raise SsgError.single("USD export needs usd-core: pip install 'ssgc[sim]'") from None
    return Gf, Usd, UsdGeom, UsdPhysics


def _geometry(stage, path: str, shape: Shape):  # type: ignore[no-untyped-def]
    Gf, _, UsdGeom, UsdPhysics = _pxr()
    if shape.kind == "box":
        prim = UsdGeom.Cube.Define(stage, path)
        prim.CreateSizeAttr(1.0)
        _place(prim, shape)
        prim.AddScaleOp(UsdGeom.XformOp.PrecisionDouble).Set(Gf.Vec3d(*shape.size))
    elif shape.kind == "cylinder":
        prim = UsdGeom.Cylinder.Define(stage, path)
        prim.CreateRadiusAttr(shape.size[0])
        prim.CreateHeightAttr(shape.size[1])
        prim.CreateAxisAttr(UsdGeom.Tokens.z)
        _place(prim, shape)
    elif shape.kind == "sphere":
        prim = UsdGeom.Sphere.Define(stage, path)
        prim.CreateRadiusAttr(shape.size[0])
        _place(prim, shape)
    else:  # the mesh's points are already placed at the geometry's origin
        prim = _mesh(stage, path, shape.mesh)
        if shape.exact_pieces or shape.boxes:  # its colliders are under ID/collision
            return
        approx = "convexDecomposition" if len(shape.collision) > 1 else "convexHull"
        UsdPhysics.MeshCollisionAPI.Apply(prim.GetPrim()).CreateApproximationAttr(approx)
    UsdPhysics.CollisionAPI.Apply(prim.GetPrim())


def _mesh(stage, path: str, mesh: object):  # type: ignore[no-untyped-def]
    Gf, _, UsdGeom, _ = _pxr()
    prim = UsdGeom.Mesh.Define(stage, path)
    prim.CreatePointsAttr([Gf.Vec3f(*map(float, v)) for v in mesh.vertices])  # type: ignore[attr-defined]
    prim.CreateFaceVertexCountsAttr([3] * len(mesh.faces))  # type: ignore[attr-defined]
    prim.CreateFaceVertexIndicesAttr([int(i) for i in np.ravel(mesh.faces)])  # type: ignore[attr-defined]
    prim.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    return prim


def _exact_pieces(stage, path: str, shape: Shape) -> None:  # type: ignore[no-untyped-def]
    """Each convex piece a collider of its own (its hull is itself), not drawn."""
    _, _, UsdGeom, UsdPhysics = _pxr()
    UsdGeom.Scope.Define(stage, path)
    for k, piece in enumerate(shape.collision):
        prim = _mesh(stage, f"{path}/piece_{k}", piece)
        prim.CreatePurposeAttr(UsdGeom.Tokens.guide)
        UsdPhysics.CollisionAPI.Apply(prim.GetPrim())
        api = UsdPhysics.MeshCollisionAPI.Apply(prim.GetPrim())
        api.CreateApproximationAttr("convexHull")


def _boxes(stage, path: str, shape: Shape) -> None:  # type: ignore[no-untyped-def]
    """A tray's boxes, each a collider `Cube` of its own, placed and scaled, not drawn."""
    Gf, _, UsdGeom, UsdPhysics = _pxr()
    UsdGeom.Scope.Define(stage, path)
    for k, (centre, sides) in enumerate(shape.boxes):
        prim = UsdGeom.Cube.Define(stage, f"{path}/box_{k}")
        prim.CreateSizeAttr(1.0)
        prim.CreatePurposeAttr(UsdGeom.Tokens.guide)
        prim.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble).Set(Gf.Vec3d(*centre))
        prim.AddScaleOp(UsdGeom.XformOp.PrecisionDouble).Set(Gf.Vec3d(*sides))
        UsdPhysics.CollisionAPI.Apply(prim.GetPrim())


def _place(prim, shape: Shape) -> None:  # type: ignore[no-untyped-def]
    """A primitive is centred on the geometry's origin in the object's frame."""
    if any(shape.origin):
        Gf, _, UsdGeom, _ = _pxr()
        op = prim.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble)
        op.Set(Gf.Vec3d(*map(float, shape.origin)))


def _body(stage, body: Body) -> None:  # type: ignore[no-untyped-def]
    Gf, _, UsdGeom, UsdPhysics = _pxr()
    xform = UsdGeom.Xform.Define(stage, f"/World/{body.name}")
    xform.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble).Set(Gf.Vec3d(*map(float, body.xyz)))
    w, x, y, z = map(float, body.quat)
    xform.AddOrientOp(UsdGeom.XformOp.PrecisionDouble).Set(Gf.Quatd(w, Gf.Vec3d(x, y, z)))
    shape = body.shape
    if shape is None:
        return
    _geometry(stage, f"/World/{body.name}/geometry", shape)
    if shape.exact_pieces:
        _exact_pieces(stage, f"/World/{body.name}/collision", shape)
    if shape.boxes:
        _boxes(stage, f"/World/{body.name}/collision", shape)
    if body.fixed:
        return
    prim = xform.GetPrim()
    UsdPhysics.RigidBodyAPI.Apply(prim)
    mass = UsdPhysics.MassAPI.Apply(prim)
    moments, axes = principal_axes(shape.inertia)
    q = matrix_to_quat(axes)
    mass.CreateMassAttr(shape.mass)
    mass.CreateCenterOfMassAttr(Gf.Vec3f(*map(float, shape.com)))
    mass.CreateDiagonalInertiaAttr(Gf.Vec3f(*map(float, moments)))
    mass.CreatePrincipalAxesAttr(Gf.Quatf(float(q[0]), Gf.Vec3f(*map(float, q[1:]))))


def usd_stage(scene: SceneBodies):  # type: ignore[no-untyped-def]
    _, Usd, UsdGeom, _ = _pxr()
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())
    for body in scene.bodies:
        _body(stage, body)
    return stage


def files(scene: SceneBodies) -> dict[str, str | bytes]:
    stage = usd_stage(scene)  # held: the layer lives only as long as its stage
    return {f"{scene.name}{SUFFIX}": stage.GetRootLayer().ExportToString()}

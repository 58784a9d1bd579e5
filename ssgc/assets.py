"""Each observed type's physical shape: geometry, collision geometry, mass and inertia.

The grammar names a primitive or a mesh file per type (`geometry:`) and how its objects behave
in a simulator (`body:`: static or free, a mass or a density, hull or convex decomposition).
This module turns that into numbers once per grammar, so the exporters and the settler never
read the grammar's YAML again.  Primitives have closed-form inertias; a mesh's mass properties
come from trimesh (the mesh must be watertight for its volume to mean anything).  A `revolve`
collides as convex pieces cut from its profile (`revolve_pieces`): its cavity stays empty
without coacd.
"""

from __future__ import annotations

import hashlib
import io
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ssgc import dsl
from ssgc.errors import Diagnostic, GrammarError, SsgError
from ssgc.io.atomic import write_bytes_atomic
from ssgc.ir import Grammar, NodeType

DEFAULT_DENSITY = 1000.0  # kg/m³, water: a type's body without mass or density
MAX_MESH_BYTES = 64 * 1024 * 1024
PRIMITIVE_SECTIONS = 32  # facets of a cylinder's or sphere's triangle mesh (GLB, USD meshes)
# A revolve's collision pieces: sectors around the axis, as few as keep every chord of its
# widest circle within CHORD_ERROR of the arc (a bowl of radius 15 cm: 28 sectors), and at
# least MIN_SECTORS so a small cup still rolls as a round one does.
CHORD_ERROR = 0.001  # m
FLOAT32_TINY = float(np.finfo(np.float32).tiny)  # masses and inertias a USD file can hold
FLOAT32_MAX = float(np.finfo(np.float32).max)
MIN_SECTORS, MAX_SECTORS = 16, 64


@dataclass(frozen=True)
class Shape:
    """One type's body in its own frame (the frame of the object's pose).

    `mesh`, `collision` and `com` are already placed at the geometry's `origin`; a primitive's
    `kind` and `size` describe it about its own centre, which is at `origin`."""

    type: str
    kind: str  # "box", "cylinder", "sphere", "mesh" (a revolve too) or "tray"
    size: tuple[float, ...]  # box: full sides; cylinder: (radius, length); sphere: (radius,)
    # tray: (x, y, z, wall)
    mesh: object  # trimesh.Trimesh: the visual surface (primitives too, as triangles)
    collision: tuple[object, ...]  # meshes: convex pieces (trimesh); primitives, trays: ()
    mass: float
    com: NDArray[np.float64]  # (3,) centre of mass in the type's frame
    inertia: NDArray[np.float64]  # (3, 3) about the centre of mass, in the type's frame
    static: bool
    source: str = ""  # a mesh's file name as the grammar writes it
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)  # the geometry's place in the frame
    # The pieces are the solid itself (a revolve's, `revolve_pieces`), not an approximation a
    # simulator may redo its own way (USD's `convexHull` / `convexDecomposition`).
    exact_pieces: bool = False
    # A tray's collision: (centre in the type's frame, full sides) of boxes that make it
    boxes: tuple[tuple[tuple[float, float, float], tuple[float, float, float]], ...] = ()

    @property
    def primitive(self) -> bool:
        """A box, cylinder or sphere, which every format has; other kinds are drawn as `mesh`
        (an OBJ file where a format names files)."""
        return self.kind in ("box", "cylinder", "sphere")


def _trimesh():  # type: ignore[no-untyped-def]
    import trimesh  # imported on use: commands that never export stay quick to start

    return trimesh


def mesh_path(grammar: Grammar, t: NodeType) -> Path:
    return Path(grammar.file).parent / t.geometry.mesh.file


def _load_mesh(path: Path, scale: float | list[float]) -> object:
    """A mesh file as one triangle mesh; `ValueError` with a reason when it cannot be used."""
    trimesh = _trimesh()
    if not path.is_file():
        raise ValueError("not found")
    if path.stat().st_size > MAX_MESH_BYTES:
        raise ValueError(f"larger than {MAX_MESH_BYTES // 2**20} MiB")
    try:
        mesh = trimesh.load(str(path), force="mesh", process=True)
    except Exception as exc:  # trimesh raises many kinds for a bad file
        raise ValueError(f"trimesh cannot read it ({type(exc).__name__}: {exc})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError("it holds no triangles")
    with np.errstate(over="ignore", invalid="ignore"):  # a huge scale: `_check_size` tells
        mesh.apply_scale(np.broadcast_to(np.asarray(scale, dtype=float), 3))
    _check_size(mesh)
    if not _encloses_a_volume(mesh):
        raise ValueError(
            "it encloses no volume (its points lie in a plane or on a line): an object needs "
            "a solid, for its mass and its collisions"
        )
    return mesh


def _check_size(mesh: object) -> None:
    """Refuse a mesh larger than the space poses may span (`dsl.MAX_COORDINATE` from the
    origin): scaled by 1e200 its volume overflowed, and its mass was then blamed on the
    density."""
    _, size = _bounds(mesh)
    if not size <= 2 * dsl.MAX_COORDINATE:  # NaN too
        raise ValueError(
            f"it is {size:g} m across once scaled, more than the "
            f"{2 * dsl.MAX_COORDINATE / 1000:,.0f} km that poses may span (each axis within "
            f"{dsl.MAX_COORDINATE / 1000:,.0f} km of the origin); check its scale"
        )


def _encloses_a_volume(mesh: object) -> bool:
    """Whether the mesh's convex hull has a volume (a flat mesh, one triangle or points on a
    line gave NaN masses or an internal error in every export).  Relative to the mesh's size:
    a hull a billionth of its bounding cube is flat for any simulator.  Measured on the mesh
    brought to unit size, so that no scale changes the answer: trimesh merges points closer
    than 1e-8 (a box scaled by 1e-6 lost its depth) and rounds coordinates to integers (a box
    scaled by 1e15 overflowed), and size**3 overflowed for a scale of 1e200."""
    unit = _unit_sized(mesh)
    if unit is None:
        return False
    try:
        with np.errstate(all="ignore"):  # a flat hull's centre of mass divides by 0
            volume = float(unit[0].convex_hull.volume)  # type: ignore[attr-defined]
    except Exception:  # qhull refuses points in a plane or on a line
        return False
    return bool(np.isfinite(volume) and volume > 1e-9)


def _unit_sized(mesh: object) -> tuple[object, NDArray[np.float64], float] | None:
    """A copy of the mesh centred on its bounding box and scaled to a largest side of 1, with
    that centre and side; None when the mesh has no finite, positive size."""
    centre, size = _bounds(mesh)
    if not (np.isfinite(size) and np.all(np.isfinite(centre)) and size > 0):
        return None
    vertices = np.asarray(mesh.vertices, dtype=float)  # type: ignore[attr-defined]
    unit = _trimesh().Trimesh((vertices - centre) / size, mesh.faces, process=False)  # type: ignore[attr-defined]
    return unit, centre, size


def _bounds(mesh: object) -> tuple[NDArray[np.float64], float]:
    """The centre of the mesh's bounding box and its largest side (inf or NaN when sides of
    1e308 overflow)."""
    vertices = np.asarray(mesh.vertices, dtype=float)  # type: ignore[attr-defined]
    with np.errstate(all="ignore"):
        low, high = vertices.min(axis=0), vertices.max(axis=0)
        return (low + high) / 2, float(np.max(high - low))


def check_assets(grammar: Grammar, text: str | None = None) -> list[Diagnostic]:
    """Located errors for every mesh that is missing or unreadable (for `ssg validate`)."""
    return _meshes(grammar, text)[1]


def _meshes(
    grammar: Grammar, text: str | None = None
) -> tuple[dict[int, object], list[Diagnostic]]:
    """Every mesh geometry loaded once, by type id, and located errors for those that cannot
    be used (reading a mesh and its hull is the slow part of a large file).

    The compiled grammar keeps document paths, not positions: the grammar text is read again
    for line and column only when there is something to report.
    """
    meshes, problems = {}, []
    for t in grammar.types:
        if isinstance(t.geometry, dsl.MeshG):
            try:
                meshes[t.id] = _load_mesh(mesh_path(grammar, t), t.geometry.mesh.scale)
            except ValueError as exc:
                loc = (*t.path, "geometry", "mesh", "file")
                problems.append((loc, f"mesh file '{t.geometry.mesh.file}': {exc}"))
    if not problems:
        return meshes, []
    from ssgc.yamlio import load_located

    if text is None:
        text = Path(grammar.file).read_text(encoding="utf-8")
    _, source = load_located(text, grammar.file)
    return meshes, [source.diagnostic(loc, message) for loc, message in problems]


def load_shapes(grammar: Grammar, collision: bool = True, masses: bool = True) -> dict[int, Shape]:
    """The shape of every observed type with geometry, by type id.

    `collision=False` skips the convex decomposition (slow) for exports that carry no
    collision geometry; `masses=False` skips the check that every mass and inertia fits a
    simulator's file, for exports that hold none (glTF).  A bad mesh, or with `masses` a mass
    out of range, is a located `GrammarError` naming every type at fault.
    """
    meshes, errors = _meshes(grammar)
    if errors:
        raise GrammarError(errors)
    shapes = {
        t.id: _shape(grammar, t, collision, meshes.get(t.id))
        for t in grammar.types
        if t.observed and t.geometry is not None
    }
    if masses:
        _check_storable(grammar, shapes)
    return shapes


def _shape(grammar: Grammar, t: NodeType, collision: bool, loaded: object | None) -> Shape:
    """`loaded`: the type's mesh geometry as `_meshes` read it (None for other kinds)."""
    trimesh = _trimesh()
    body = t.body if t.body is not None else dsl.Body()
    g = t.geometry
    origin = np.asarray(g.origin, float)
    boxes: tuple[tuple[tuple[float, float, float], tuple[float, float, float]], ...] = ()
    if isinstance(g, dsl.MeshG | dsl.RevolveG):  # a revolve's surface is a mesh to exporters
        if isinstance(g, dsl.MeshG):
            mesh, source = loaded, g.mesh.file
        else:
            mesh, source = _revolve_mesh(trimesh, g), ""
        mesh.apply_translation(origin)  # type: ignore[attr-defined]
        volume, com, unit_inertia = _mesh_mass_properties(mesh, isinstance(g, dsl.RevolveG))
        exact = isinstance(g, dsl.RevolveG) and body.collision is None
        if not collision:
            pieces: tuple[object, ...] = ()
        elif exact:
            pieces = tuple(p.apply_translation(origin) for p in revolve_pieces(g.revolve.profile))
        else:
            pieces = _collision_pieces(mesh, body.collision or "hull", t.name)
        kind, size = "mesh", ()
    elif isinstance(g, dsl.TrayG):  # drawn as its mesh, colliding as its five boxes
        kind, size = "tray", (*map(float, g.tray.size), float(g.tray.wall))
        vertices, faces = g.tray.mesh()
        mesh = trimesh.Trimesh(vertices + origin, faces, process=False)
        boxes = tuple(
            (tuple(map(float, np.add(centre, origin))), tuple(map(float, sides)))
            for centre, sides in g.tray.boxes()
        )
        volume, com, unit_inertia = _boxes_mass_properties(boxes)
        pieces, source, exact = (), "", False
    else:
        kind, size = _primitive(g)
        mesh = _primitive_mesh(trimesh, kind, size)
        mesh.apply_translation(origin)  # type: ignore[attr-defined]
        volume, unit_inertia = _primitive_mass_properties(kind, size)
        com, pieces, source, exact = origin.copy(), (), "", False
    mass = body.mass if body.mass is not None else (body.density or DEFAULT_DENSITY) * volume
    with np.errstate(over="ignore", invalid="ignore", under="ignore"):  # told below
        inertia = mass * unit_inertia
    return Shape(
        t.name,
        kind,
        size,
        mesh,
        pieces,
        float(mass),
        com,
        inertia,
        body.static,
        source,
        (float(origin[0]), float(origin[1]), float(origin[2])),
        exact,
        boxes,
    )


def _check_storable(grammar: Grammar, shapes: dict[int, Shape]) -> None:
    """Refuse masses or inertias that a simulator's file cannot hold, every type at fault in
    one error, each at its `body` (or its `geometry`, whose size made the mass).  USD stores
    them as 32-bit floats: 1e300 kg became inf there (and Drake refused its inertia as not
    physically valid), and 1e-300 kg became 0, which USD reads as "no mass given"."""
    problems = []
    for type_id, shape in shapes.items():
        if _storable(shape.mass, shape.inertia):
            continue
        t = grammar.types[type_id]
        loc = (*t.path, "body" if t.body is not None else "geometry")
        problems.append(
            (
                loc,
                f"type '{t.name}': its mass ({shape.mass:.3g} kg) or its moments of inertia "
                f"are outside what simulators' files hold (32-bit floats, {FLOAT32_TINY:.2g} "
                f"to {FLOAT32_MAX:.2g}); give it a mass, density or size in a physical range",
            )
        )
    if problems:
        raise GrammarError(_located(grammar, problems))


def _storable(mass: float, inertia: NDArray[np.float64]) -> bool:
    with np.errstate(all="ignore"):
        moments = np.linalg.eigvalsh(inertia) if np.all(np.isfinite(inertia)) else [np.inf]
    values = np.abs(np.array([mass, *moments], float))
    return bool(np.all((values >= FLOAT32_TINY) & (values <= FLOAT32_MAX)))


def _located(grammar: Grammar, problems: list[tuple[tuple, str]]) -> list[Diagnostic]:
    """Diagnostics at places of the grammar file, read again only when there is something to
    report; at the file alone when it cannot be read back."""
    from ssgc.yamlio import load_located

    try:
        text = Path(grammar.file).read_text(encoding="utf-8")
        _, source = load_located(text, grammar.file)
    except Exception:  # the file changed or went since it was compiled
        return [Diagnostic(message, grammar.file) for _, message in problems]
    return [source.diagnostic(loc, message) for loc, message in problems]


def _revolve_mesh(trimesh, g: dsl.RevolveG) -> object:  # type: ignore[no-untyped-def]
    """A revolve's closed surface (ssgc/constraints/revolved.py) as a triangle mesh."""
    from ssgc.constraints.revolved import Revolved

    vertices, faces = Revolved(g.revolve.profile).mesh(PRIMITIVE_SECTIONS)
    return trimesh.Trimesh(vertices, faces, process=True)


def revolve_sectors(radius: float) -> int:
    """How many sectors around the axis a revolve of largest radius `radius` is cut into: the
    fewest whose chords stay within CHORD_ERROR of its widest circle (a chord of a sector of
    angle a is r (1 - cos(a / 2)) from the arc), within [MIN_SECTORS, MAX_SECTORS]."""
    half_angle = np.arccos(np.clip(1.0 - CHORD_ERROR / max(radius, 1e-300), -1.0, 1.0))
    return int(np.clip(np.ceil(np.pi / max(half_angle, 1e-12)), MIN_SECTORS, MAX_SECTORS))


def profile_trapezoids(profile: object) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """A revolve's profile polygon (the axis closes it) cut into convex trapezoids, exactly.

    Cut at every vertex's height, each slab between two heights is crossed by straight edges
    only, and the inside of the polygon is between the 1st and 2nd of them (sorted by r), the
    3rd and 4th, ...; a trapezoid is one such pair.  The same pair of edges in the slab above
    continues the same trapezoid, so a dish's wall is one trapezoid per straight stretch.
    Returns (m, 6) [r_left_bottom, r_right_bottom, r_left_top, r_right_top, z_bottom, z_top]
    and (m,) whether its left side is the axis (a full turn of it is convex: a cone's frustum).
    Trapezoids of no width (a profile that touches itself) are dropped."""
    a = np.asarray(profile, float)
    b = np.roll(a, -1, axis=0)  # edge k from point k to k + 1; the last, back along the axis
    axis_edge = len(a) - 1
    levels = np.unique(a[:, 1])
    z0, z1 = levels[:-1], levels[1:]
    low, high = np.minimum(a[:, 1], b[:, 1]), np.maximum(a[:, 1], b[:, 1])
    crosses = (low[:, None] <= z0) & (high[:, None] >= z1)  # (edges, slabs): never a flat edge
    with np.errstate(divide="ignore", invalid="ignore"):  # flat edges' r: never used
        slope = (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
        r0 = a[:, 0, None] + (z0 - a[:, 1, None]) * slope[:, None]
        r1 = a[:, 0, None] + (z1 - a[:, 1, None]) * slope[:, None]
    done: list[list[float]] = []
    sides: list[bool] = []
    growing: dict[tuple[int, int], list[float]] = {}
    for s in range(len(z0)):
        edges = np.flatnonzero(crosses[:, s])
        edges = edges[np.argsort(r0[edges, s] + r1[edges, s], kind="stable")]
        now = {}
        for left, right in zip(edges[0::2].tolist(), edges[1::2].tolist(), strict=True):
            t = growing.pop((left, right), None)
            if t is None:
                t = [r0[left, s], r0[right, s], 0.0, 0.0, z0[s], 0.0]
            t[2], t[3], t[5] = r1[left, s], r1[right, s], z1[s]
            now[(left, right)] = t
        for (left, _), t in growing.items():
            done.append(t)
            sides.append(left == axis_edge)
        growing = now
    for (left, _), t in growing.items():
        done.append(t)
        sides.append(left == axis_edge)
    out = np.array(done, dtype=float).reshape(-1, 6)
    wide = np.maximum(out[:, 1] - out[:, 0], out[:, 3] - out[:, 2]) > 0
    return out[wide], np.array(sides, dtype=bool)[wide]


# The 6 faces of a piece (8 corners: a trapezoid's 4, bottom-left, bottom-right, top-left,
# top-right, at the sector's first angle, then at its second), as outward triangles.
_QUADS = np.array(
    [[0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3], [0, 1, 3, 2], [4, 6, 7, 5]]
)
_PIECE_FACES = np.concatenate([_QUADS[:, [0, 1, 2]], _QUADS[:, [0, 2, 3]]])


def revolve_pieces(profile: object, sectors: int | None = None) -> list[object]:
    """A revolve's solid as convex triangle meshes (trimesh), about its own origin.

    A convex hull fills a bowl's cavity (a cup resting in it is inside its collision solid,
    and a simulator throws it out); coacd's pieces are approximate and slow.  These are exact
    up to the chords around the axis: each trapezoid of the profile (`profile_trapezoids`)
    turned through one of `sectors` equal sectors is the convex hull of its 8 corners, and the
    pieces tile the solid with facets at the same chords as its mesh of that many sections
    (within CHORD_ERROR of the round surface by default: `revolve_sectors`).  A trapezoid on
    the axis is convex turned all the way round, so it is one piece (a dish's base)."""
    trimesh = _trimesh()
    rz = np.asarray(profile, float)
    k = sectors or revolve_sectors(float(rz[:, 0].max()))
    trapezoids, on_axis = profile_trapezoids(rz)
    pieces = []
    for r_bottom, r_top, z0, z1 in trapezoids[on_axis][:, [1, 3, 4, 5]]:
        rim = [[r, z] for r, z in ((r_bottom, z0), (r_top, z1)) if r > 0]  # a cone's tip: none
        ring = [[0.0, z0], *rim, [0.0, z1]]
        pieces.append(_turned(trimesh, ring, k))
    ring = trapezoids[~on_axis]
    angle = 2 * np.pi * (np.arange(k)[:, None] + np.arange(2)) / k  # (k, 2) each sector's ends
    r = ring[:, None, None, :4]  # (m, 1, 1, 4) its corners' radii and heights
    z = np.broadcast_to(ring[:, None, None, [4, 4, 5, 5]], (len(ring), k, 2, 4))
    corners = np.stack(
        [r * np.cos(angle)[None, :, :, None], r * np.sin(angle)[None, :, :, None], z], axis=-1
    ).reshape(-1, 8, 3)
    pointed = np.repeat((ring[:, 0] == ring[:, 1]) | (ring[:, 2] == ring[:, 3]), k)
    for v, point in zip(corners, pointed, strict=True):
        # a side of no width (a pointed rim) doubles two corners: merged, its faces dropped
        pieces.append(trimesh.Trimesh(v, _PIECE_FACES, process=bool(point), validate=bool(point)))
    return pieces


def _turned(trimesh, ring: list[list[float]], sectors: int) -> object:  # type: ignore[no-untyped-def]
    """A profile on the axis turned all the way round (a frustum or a cone), as a mesh."""
    from ssgc.constraints.revolved import Revolved

    vertices, faces = Revolved(ring).mesh(sectors)
    return trimesh.Trimesh(vertices, faces, process=False)


def _primitive(g: object) -> tuple[str, tuple[float, ...]]:
    if isinstance(g, dsl.BoxG):
        return "box", tuple(float(v) for v in g.box.size)
    if isinstance(g, dsl.CylinderG):
        return "cylinder", (float(g.cylinder.radius), float(g.cylinder.length))
    if isinstance(g, dsl.SphereG):
        return "sphere", (float(g.sphere.radius),)
    raise TypeError(f"unknown geometry {g!r}")


def _primitive_mesh(trimesh, kind: str, size: tuple[float, ...]) -> object:  # type: ignore[no-untyped-def]
    if kind == "box":
        return trimesh.creation.box(extents=size)
    if kind == "cylinder":
        return trimesh.creation.cylinder(
            radius=size[0], height=size[1], sections=PRIMITIVE_SECTIONS
        )
    return trimesh.creation.icosphere(subdivisions=3, radius=size[0])


def _primitive_mass_properties(
    kind: str, size: tuple[float, ...]
) -> tuple[float, NDArray[np.float64]]:
    """Volume and inertia per unit mass about the centre, in closed form."""
    if kind == "box":
        x, y, z = size
        return x * y * z, np.diag([y * y + z * z, x * x + z * z, x * x + y * y]) / 12.0
    if kind == "cylinder":
        r, h = size
        side = (3 * r * r + h * h) / 12.0
        return np.pi * r * r * h, np.diag([side, side, r * r / 2.0])
    r = size[0]
    return 4.0 / 3.0 * np.pi * r**3, np.eye(3) * (2.0 / 5.0 * r * r)


def _boxes_mass_properties(
    boxes: tuple[tuple[tuple[float, float, float], tuple[float, float, float]], ...],
) -> tuple[float, NDArray[np.float64], NDArray[np.float64]]:
    """Volume, centre of mass and inertia per unit mass (about the centre of mass) of boxes
    that do not overlap (a tray's), in closed form: each box's own, moved to the common centre
    of mass (parallel axes)."""
    centres = np.array([c for c, _ in boxes], float)
    sides = np.array([s for _, s in boxes], float)
    volumes = np.prod(sides, axis=1)
    volume = float(volumes.sum())
    com = volumes @ centres / volume
    squares = sides**2
    own = np.stack(
        [squares[:, [1, 2]].sum(1), squares[:, [0, 2]].sum(1), squares[:, [0, 1]].sum(1)]
    )
    d = centres - com
    shifted = np.einsum(
        "b,bij->ij",
        volumes,
        np.eye(3) * (d * d).sum(1)[:, None, None] - d[:, :, None] * d[:, None, :],
    )
    inertia = np.diag(volumes @ own.T / 12.0) + shifted
    return volume, com, inertia / volume


def _mesh_mass_properties(
    mesh: object, closed: bool = False
) -> tuple[float, NDArray[np.float64], NDArray[np.float64]]:
    """Volume, centre of mass and inertia per unit mass (about the centre of mass).

    `closed`: the mesh is a closed, consistently oriented surface by construction (a
    revolve), whose integrals are exact also where it touches itself (a profile pinched to a
    point, or doubling back on itself), which trimesh does not call a volume: its hull was
    32% and 72% too heavy.

    A mesh that does not enclose a volume (open, inside out, or with faces wound both ways,
    which halved a cube's mass) falls back to its convex hull, which does (`_load_mesh`
    refuses a flat one): a simulator needs a positive mass and a valid inertia.

    Computed on the mesh brought to unit size and scaled back (volume by size³, centre of
    mass by size, inertia per unit mass by size²), for the reasons `_encloses_a_volume` gives.
    """
    unit_sized = _unit_sized(mesh)
    if unit_sized is None:  # `_load_mesh` refuses such a mesh; a revolve always has a size
        raise ValueError("the mesh has no finite size")
    unit, centre, size = unit_sized
    own = unit.is_volume or (closed and unit.volume > 0)  # type: ignore[attr-defined]
    solid = unit if own else unit.convex_hull  # type: ignore[attr-defined]
    with np.errstate(over="ignore"):  # a size of 1e200: an infinite mass, refused in our words
        volume = float(solid.volume) * np.float64(size) ** 3
        com = centre + size * np.asarray(solid.center_mass, dtype=float)
        per_mass = np.asarray(solid.moment_inertia, dtype=float) / (solid.density * solid.volume)
        return volume, com, per_mass * np.float64(size) ** 2


def _collision_pieces(mesh: object, how: str, name: str) -> tuple[object, ...]:
    """Convex pieces that stand for the mesh in collisions: its hull (a revolve's too, when
    the grammar asks for `hull`: cavity filled), or coacd's decomposition."""
    if how == "hull":
        return (_hull(mesh),)
    try:
        import coacd  # type: ignore[import-not-found]
    except ImportError:
        raise SsgError.single(
            f"type '{name}' asks for a convex decomposition, which needs coacd: "
            "pip install 'ssgc[sim]'"
        ) from None
    return _decompose(coacd, mesh)


def _hull(mesh: object) -> object:
    """The mesh's convex hull, found on the mesh brought to unit size and scaled back: trimesh
    merges points closer than 1e-8, so a teacup scaled by 1e-5 had a hull of no triangle (and
    its objects no collision geometry)."""
    unit = _unit_sized(mesh)
    if unit is None:  # `_load_mesh` refuses such meshes; a revolve always has a size
        return mesh.convex_hull  # type: ignore[attr-defined]
    shape, centre, size = unit
    hull = shape.convex_hull.copy()  # type: ignore[attr-defined]
    hull.vertices = np.asarray(hull.vertices) * size + centre
    return hull


COACD_OPTIONS = {  # few pieces, quickly: dishes, not precision parts
    "threshold": 0.1,
    "max_convex_hull": 8,
    "preprocess_mode": "off",
    "resolution": 1000,
    "mcts_iterations": 50,
    "mcts_max_depth": 2,
    "mcts_nodes": 10,
    "seed": 0,
}
_DECOMPOSED: dict[str, tuple[object, ...]] = {}


def _cache_dir() -> Path:
    root = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(root) / "ssgc" / "coacd"


def _decompose(coacd, mesh) -> tuple[object, ...]:  # type: ignore[no-untyped-def]
    """coacd's convex pieces of a mesh, each as its convex hull.

    A decomposition takes seconds, so it is cached in memory and on disk (under
    ~/.cache/ssgc/coacd, keyed by the mesh's vertices, faces and the options); a cache that
    cannot be read or written is simply not used.
    """
    trimesh = _trimesh()
    digest = hashlib.sha256(
        np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes()
        + np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes()
        + repr(sorted(COACD_OPTIONS.items())).encode()
    ).hexdigest()
    if digest in _DECOMPOSED:
        return _DECOMPOSED[digest]
    file = _cache_dir() / f"{digest}.npz"
    parts = None
    try:
        with np.load(file) as data:
            parts = [(data[f"v{i}"], data[f"f{i}"]) for i in range(len(data.files) // 2)]
    except (OSError, ValueError, KeyError):
        pass
    if not parts:
        coacd.set_log_level("error")
        found = coacd.run_coacd(coacd.Mesh(mesh.vertices, mesh.faces), **COACD_OPTIONS)
        parts = [(np.asarray(v, dtype=float), np.asarray(f, dtype=np.int64)) for v, f in found]
        arrays = {f"{k}{i}": a for i, (v, f) in enumerate(parts) for k, a in (("v", v), ("f", f))}
        try:
            file.parent.mkdir(parents=True, exist_ok=True)
            buf = io.BytesIO()
            np.savez(buf, **arrays)
            write_bytes_atomic(file, buf.getvalue())
        except OSError:
            pass
    pieces = tuple(trimesh.Trimesh(v, f).convex_hull for v, f in parts)
    _DECOMPOSED[digest] = pieces
    return pieces


def check_document_meshes(path: Path, allow_outside: bool = False) -> list[Diagnostic]:
    """Located errors for every missing or unreadable mesh of a grammar file that does not
    compile (for `ssg validate`, so one run reports them with the grammar's other errors).

    Read from the document itself: every `geometry: {mesh: {file}}` of a type whose file name
    is a plain relative name inside the grammar's directory (other names the compiler already
    reports), with its `scale` when that is well formed.
    """
    from ssgc.yamlio import MAX_GRAMMAR_BYTES, load_located, read_text

    try:  # within the compiler's size limit: a file over it is that error alone
        text = read_text(path, MAX_GRAMMAR_BYTES, "grammar file")
        data, source = load_located(text, str(path))
    except Exception:  # unreadable or not YAML: the compiler's messages say so
        return []
    types = data.get("types") if isinstance(data, dict) else None
    if not isinstance(types, dict):
        return []
    base = path.parent.resolve()
    problems = []
    for name, body in types.items():
        geometry = body.get("geometry") if isinstance(body, dict) else None
        mesh = geometry.get("mesh") if isinstance(geometry, dict) else None
        file = mesh.get("file") if isinstance(mesh, dict) else None
        if not isinstance(file, str) or not file or Path(file).is_absolute():
            continue
        target = (path.parent / file).resolve()
        if not allow_outside and not target.is_relative_to(base):
            continue
        scale = _usable_scale(mesh.get("scale", 1.0))
        try:
            _load_mesh(path.parent / file, scale.tolist())
        except ValueError as exc:
            loc = ("types", name, "geometry", "mesh", "file")
            problems.append(source.diagnostic(loc, f"mesh file '{file}': {exc}"))
    return problems


def _usable_scale(scale: object) -> NDArray[np.float64]:
    """A mesh's `scale` as three factors; 1 when it is not three finite, positive numbers
    (the compiler reports that: a scale of 0 or NaN also read as a flat mesh was one mistake
    told twice)."""
    try:
        factors = np.broadcast_to(np.asarray(scale, dtype=float), 3)
    except (TypeError, ValueError):
        return np.ones(3)
    return factors if bool(np.all(np.isfinite(factors) & (factors > 0))) else np.ones(3)

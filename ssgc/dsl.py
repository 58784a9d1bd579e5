"""The YAML grammar language, as pydantic v2 models.

These models check the *shape* of a grammar document (keys, types, finite numbers, one choice
per union).  Everything that needs the whole document (unknown child types, recursion bounds,
normalisable probabilities, orthogonal matrices, ...) is checked by `ssgc.compile`.

Unions are written the way people write YAML by hand: a bare word (``same``, ``uniform``) or a
mapping with exactly one key naming the variant (``{world_normal: {...}}``).  The
discriminator below turns that into one clear error instead of pydantic's per-variant noise.
The docs (docs/grammar.md) are the user-facing reference for this file.
"""

from __future__ import annotations

import difflib
from typing import Annotated, Any, Literal, Union

from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Discriminator,
    Field,
    StringConstraints,
    Tag,
    model_validator,
)
from pydantic.fields import FieldInfo
from pydantic_core import PydanticCustomError

Finite = Annotated[float, Field(allow_inf_nan=False)]
Positive = Annotated[float, Field(allow_inf_nan=False, gt=0)]
NonNegative = Annotated[float, Field(allow_inf_nan=False, ge=0)]
Probability = Annotated[float, Field(allow_inf_nan=False, ge=0, le=1)]
Vec3 = Annotated[list[Finite], Field(min_length=3, max_length=3)]
Vec4 = Annotated[list[Finite], Field(min_length=4, max_length=4)]
Mat3 = Annotated[list[Vec3], Field(min_length=3, max_length=3)]
# m: the farthest a pose may lie from the origin on an axis.  Poses are resolved to POS_TOL
# (1e-6 m); at 1e10 m one float64 step is 2e-6 m, and sampled scenes were called infeasible.
MAX_COORDINATE = 1e6


def _within_limit(xyz: list[float], what: str) -> list[float]:
    far = max(abs(v) for v in xyz)
    if far > MAX_COORDINATE:
        raise ValueError(
            f"{what} must lie within {MAX_COORDINATE / 1000:,.0f} km of the origin on each "
            f"axis, got {_digits(far)} m (poses are resolved to 1e-6 m, which floating point "
            "cannot hold there)"
        )
    return xyz


def _digits(x: float) -> str:
    """`x` short (2e+06), or with every digit where short would round it to the limit
    (1000000.0000001 read as "got 1e+06 m", the limit itself)."""
    short = f"{x:g}"
    return short if float(short) == x else repr(x)


def _near_origin(xyz: list[float]) -> list[float]:
    return _within_limit(xyz, "a position")


def _near_parent(xyz: list[float]) -> list[float]:
    """A rule's constant (an offset, a Normal's mean, a box corner; the clutter region) is
    bounded as a position is: every scene reader refuses a pose beyond the limit, so a rule
    placing its child there made scenes no command reads.  Each constant is bounded on its own;
    what spreads and chained offsets add up to, `ssg sample` checks on the scenes it writes."""
    return _within_limit(xyz, "a position or offset")


def _within(limit: float, what: str) -> Any:
    """A check that a geometry's number is at most `limit` (in size): a shape is bounded as a
    mesh is (`ssgc.assets`), to the 2,000 km that poses may span.  Sizes of 1e200 reached FCL
    (`non_penetration`), which printed Eigen's "too many iterations" hundreds of times and
    let the grammar pass; the limit is checked before any library sees the number."""

    def check(v: float) -> float:
        if abs(v) > limit:
            raise ValueError(
                f"{what} must be at most {limit / 1000:,.0f} km ({limit:g} m), got {v:g} m: "
                f"poses span {2 * MAX_COORDINATE / 1000:,.0f} km (each axis within "
                f"{MAX_COORDINATE / 1000:,.0f} km of the origin)"
            )
        return v

    return check


# m: a geometry's side or length (a box, a tray, a cylinder) is at most the span of poses, a
# radius half of it, a `revolve` profile's coordinate (r, z) at most MAX_COORDINATE either way
Length = Annotated[Positive, AfterValidator(_within(2 * MAX_COORDINATE, "a geometry's size"))]
Radius = Annotated[Positive, AfterValidator(_within(MAX_COORDINATE, "a radius"))]
ProfileCoordinate = Annotated[
    Finite, AfterValidator(_within(MAX_COORDINATE, "a profile coordinate"))
]

Position = Annotated[Vec3, AfterValidator(_near_origin)]
# a position or offset written in a rule (an `offset`, a Normal's `mean`, a box corner)
RulePosition = Annotated[Vec3, AfterValidator(_near_parent)]
Mat4 = Annotated[list[Vec4], Field(min_length=4, max_length=4)]
Axis = Literal["x", "y", "z"]
TypeName = Annotated[str, StringConstraints(pattern=r"^[A-Za-z_][A-Za-z0-9_]*$", max_length=200)]


class Strict(BaseModel):
    """Base: unknown keys are errors and nothing is coerced (``"0.5"`` is not a number)."""

    model_config = ConfigDict(extra="forbid", strict=True, populate_by_name=True)

    @model_validator(mode="before")
    @classmethod
    def _known_keys(cls, data: Any) -> Any:
        """Name the unknown key and what was expected (pydantic only says 'extra input')."""
        if isinstance(data, dict):
            allowed = sorted(f.alias or name for name, f in cls.model_fields.items())
            for key in data:
                if key not in allowed:
                    raise unknown_key_error(str(key), allowed)
        return data


def unknown_key_error(key: str, allowed: list[str]) -> PydanticCustomError:
    """The error of one unknown key (the compiler also makes it for the other unknown keys
    of a mapping, whose check stops at the first)."""
    close = difflib.get_close_matches(key, allowed, n=1)
    return PydanticCustomError(
        "unknown_key",
        "unknown key '{key}'; expected one of: {allowed}{hint}",
        {
            "key": key,
            "allowed": ", ".join(allowed),
            "hint": f" (did you mean '{close[0]}'?)" if close else "",
        },
    )


# --------------------------------------------------------------------------------- poses ---


class Orientation(Strict):
    """A rotation written one of three ways; none given means the identity."""

    rpy: Vec3 | None = Field(None, description="Roll-pitch-yaw in radians, R = Rz(y) Ry(p) Rx(r).")
    rpy_deg: Vec3 | None = Field(None, description="Roll-pitch-yaw in degrees.")
    quat_wxyz: Vec4 | None = Field(None, description="Unit quaternion, scalar first.")

    @model_validator(mode="after")
    def _one_form(self) -> Orientation:
        given = [k for k in ("rpy", "rpy_deg", "quat_wxyz") if getattr(self, k) is not None]
        if len(given) > 1:
            raise ValueError(f"give the rotation one way only, got {' and '.join(given)}")
        return self


class Pose(Orientation):
    xyz: Position = Field(
        default_factory=lambda: [0.0, 0.0, 0.0], description="Position in meters."
    )


# ----------------------------------------------------------------------- discriminators ---


def one_key(value: Any) -> str | None:
    """Tag of a bare-word-or-single-key-mapping union: the word, or the mapping's only key."""
    if isinstance(value, str):
        return value
    if isinstance(value, dict) and len(value) == 1:
        return next(iter(value))
    if isinstance(value, BaseModel):  # already validated (model construction in code)
        fields = [k for k, v in value.__dict__.items() if v is not None]
        return fields[0] if len(fields) == 1 else None
    return None


def _choice(*variants: tuple[Any, str], what: str) -> Any:
    """Build ``Annotated[Union[...], Discriminator]`` for a one-key union."""
    names = ", ".join(tag for _, tag in variants)
    members = tuple(Annotated[tp, Tag(tag)] for tp, tag in variants)
    return Annotated[
        members[0] if len(members) == 1 else Union[members],  # noqa: UP007
        Discriminator(
            one_key,
            custom_error_type="invalid_choice",
            custom_error_message=f"expected a {what}: one of {names}",
        ),
    ]


# ------------------------------------------------------------------------ translations ---


class NormalParams(Strict):
    """A Normal law on a 3-D offset; pinned axes are held at the mean (density over the rest)."""

    mean: RulePosition = Field(default_factory=lambda: [0.0, 0.0, 0.0])
    variance: Positive | Vec3 | None = Field(
        None, description="Per-axis variances (m^2), or one number for all axes."
    )
    covariance: Mat3 | None = Field(None, description="Full 3x3 covariance (m^2).")
    pin: list[Axis] = Field(default_factory=list, description="Axes held exactly at the mean.")
    fixed: bool = Field(False, description="Keep these parameters when fitting.")

    @model_validator(mode="after")
    def _one_spread(self) -> NormalParams:
        if (self.variance is None) == (self.covariance is None):
            raise ValueError("give exactly one of `variance` or `covariance`")
        return self


class BoxParams(Strict):
    """Uniform on an axis-aligned box; an axis with min == max is pinned."""

    min: RulePosition
    max: RulePosition
    fixed: bool = False


class OffsetT(Strict):
    offset: RulePosition = Field(description="Fixed offset, in the parent's frame.")


class WorldNormalT(Strict):
    world_normal: NormalParams = Field(description="Child position ~ Normal in the world frame.")


class WorldNormalOffsetT(Strict):
    world_normal_offset: NormalParams = Field(
        description="Child position = parent position + Normal offset along world axes."
    )


class ParentNormalOffsetT(Strict):
    parent_normal_offset: NormalParams = Field(
        description="Child position = parent position + parent rotation * Normal offset."
    )


class WorldBoxT(Strict):
    world_box: BoxParams = Field(description="Child position uniform in a world-frame box.")


class WorldBoxOffsetT(Strict):
    world_box_offset: BoxParams = Field(
        description="Child position = parent position + offset uniform in a world-axis box."
    )


_CHOICES: dict[str, list[tuple[Any, str]]] = {
    "translation": [
        (Literal["same"], "same"),
        (OffsetT, "offset"),
        (WorldNormalT, "world_normal"),
        (WorldNormalOffsetT, "world_normal_offset"),
        (ParentNormalOffsetT, "parent_normal_offset"),
        (WorldBoxT, "world_box"),
        (WorldBoxOffsetT, "world_box_offset"),
    ]
}
Translation = _choice(*_CHOICES["translation"], what="translation rule")


# --------------------------------------------------------------------------- rotations ---


Concentrations = Annotated[list[NonNegative], Field(min_length=3, max_length=3)]


class BinghamParams(Strict):
    """A Bingham law on unit quaternions: a mode and concentrations, or raw (M, Z)."""

    mode: Orientation | None = Field(None, description="Most likely rotation (default identity).")
    concentration: NonNegative | Concentrations | None = Field(
        None,
        description="Concentration about the mode frame's x, y, z axes "
        "(angular std ~ sqrt(2/c) rad).",
    )
    M: Mat4 | None = Field(None, description="Orthogonal 4x4 matrix, columns are axes (wxyz).")
    Z: Vec4 | None = Field(None, description="Log-density weights of M's columns (largest = mode).")
    fixed: bool = False

    @model_validator(mode="after")
    def _one_form(self) -> BinghamParams:
        raw = self.M is not None or self.Z is not None
        moded = self.mode is not None or self.concentration is not None
        if raw and moded:
            raise ValueError("give either `mode`/`concentration` or raw `M`/`Z`, not both")
        if raw and (self.M is None or self.Z is None):
            raise ValueError("raw Bingham parameters need both `M` and `Z`")
        if not raw and self.concentration is None:
            raise ValueError("give `concentration` (with an optional `mode`), or raw `M` and `Z`")
        return self


class RevoluteParams(Strict):
    """Child rotation = parent rotation * rotation by a uniform angle about `axis`."""

    axis: Vec3 = Field(default_factory=lambda: [0.0, 0.0, 1.0])
    min: Finite = Field(-3.141592653589793, description="Smallest angle (rad).")
    max: Finite = Field(3.141592653589793, description="Largest angle (rad).")
    fixed: bool = False


class OffsetR(Strict):
    offset: Orientation = Field(description="Fixed rotation offset, in the parent's frame.")


class WorldBinghamR(Strict):
    world_bingham: BinghamParams


class ParentBinghamR(Strict):
    parent_bingham: BinghamParams


class RevoluteR(Strict):
    revolute: RevoluteParams


_CHOICES["rotation"] = [
    (Literal["same"], "same"),
    (Literal["uniform"], "uniform"),
    (OffsetR, "offset"),
    (WorldBinghamR, "world_bingham"),
    (ParentBinghamR, "parent_bingham"),
    (RevoluteR, "revolute"),
]
Rotation = _choice(*_CHOICES["rotation"], what="rotation rule")


# ------------------------------------------------------------------------------ rules ---


class Rule(Strict):
    """Produce one child: its type, and how its pose follows from the parent's."""

    child: TypeName
    p: NonNegative | None = Field(
        None,
        description="`or`: weight (weights are normalised); `independent`: probability of firing.",
    )
    translation: Translation = "same"  # type: ignore[valid-type]
    rotation: Rotation = "same"  # type: ignore[valid-type]


class GeometricCount(Strict):
    p: Annotated[float, Field(allow_inf_nan=False, gt=0, le=1)] = Field(
        description="Stopping probability: P(n) ~ p (1-p)^(n-start)."
    )
    max: Annotated[int, Field(ge=0, le=1000)]
    start: Annotated[int, Field(ge=0)] = 0


class ProbsCount(Strict):
    probs: Annotated[list[NonNegative], Field(min_length=1, max_length=1001)] = Field(
        description="P(count = n) for n = 0 .. len-1 (normalised)."
    )


class GeometricCountSpec(Strict):
    geometric: GeometricCount


Count = _choice((ProbsCount, "probs"), (GeometricCountSpec, "geometric"), what="count law")


class Repeat(Strict):
    count: Count  # type: ignore[valid-type]
    rule: Rule


class BoxGeometry(Strict):
    size: Annotated[list[Length], Field(min_length=3, max_length=3)]


class CylinderGeometry(Strict):
    radius: Radius
    length: Length


class SphereGeometry(Strict):
    radius: Radius


class MeshGeometry(Strict):
    file: Annotated[str, StringConstraints(min_length=1)]
    scale: Positive | Annotated[list[Positive], Field(min_length=3, max_length=3)] = 1.0


class RevolveGeometry(Strict):
    """A solid of revolution (a dish): its cross-section, turned about the geometry's z axis."""

    profile: list[Annotated[list[ProfileCoordinate], Field(min_length=2, max_length=2)]] = Field(
        description="[r, z] points in metres from a point on the axis (r = 0), around the "
        "material, back to the axis; the axis closes it."
    )

    @model_validator(mode="after")
    def _solid(self) -> RevolveGeometry:
        from ssgc.geometry import profile_problem

        problem = profile_problem(self.profile)
        if problem is not None:
            raise ValueError(problem)
        return self


class TrayGeometry(Strict):
    """An open-topped box (a bin, a tray, a drawer): a floor and four walls, each `wall` thick,
    open towards +z.  A box standing for it is solid: what rests in the bin is inside that
    box, and a simulator throws it out.  Centred on the geometry's origin, as a box is: `size`
    is its outside, so its floor's top is at z = wall - size_z / 2 and its rim at size_z / 2."""

    size: Annotated[list[Length], Field(min_length=3, max_length=3)] = Field(
        description="Outside lengths along x, y, z, metres (the walls and floor inside them)."
    )
    wall: Length = Field(description="Thickness of the floor and of each wall, metres.")

    @model_validator(mode="after")
    def _room_inside(self) -> TrayGeometry:
        x, y, z = self.size
        if not (2 * self.wall < min(x, y) and self.wall < z):
            raise ValueError(
                f"a tray's wall ({self.wall:g} m) leaves no room inside its size "
                f"[{x:g}, {y:g}, {z:g}]: twice the wall must be less than x and y, and the wall "
                "less than z"
            )
        return self

    def boxes(self) -> list[tuple[tuple[float, float, float], tuple[float, float, float]]]:
        """(centre, full sides) of the five boxes that make it, which do not overlap: the floor,
        then the walls at -x, +x (full length in y), -y, +y (between those)."""
        x, y, z = self.size
        w = self.wall
        up, high = w / 2, z - w  # the walls stand on the floor: centred w / 2 above the middle
        return [
            ((0.0, 0.0, (w - z) / 2), (x, y, w)),
            ((-(x - w) / 2, 0.0, up), (w, y, high)),
            (((x - w) / 2, 0.0, up), (w, y, high)),
            ((0.0, -(y - w) / 2, up), (x - 2 * w, w, high)),
            ((0.0, (y - w) / 2, up), (x - 2 * w, w, high)),
        ]

    def mesh(self) -> tuple[Any, Any]:
        """(vertices (16, 3), triangles (28, 3)) of its closed surface, facing outwards: four
        rectangles (outside bottom, outside top, inside top, floor top) joined in turn, the
        outside bottom and the floor closed."""
        import numpy as np

        x, y, z = (v / 2 for v in self.size)
        w = self.wall
        corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float)  # counter-clockwise
        rings = [(x, y, -z), (x, y, z), (x - w, y - w, z), (x - w, y - w, w - z)]
        vertices = np.concatenate([np.c_[corners * (a, b), np.full(4, c)] for a, b, c in rings])
        j, k = np.arange(4), (np.arange(4) + 1) % 4
        quads = [
            np.stack([4 * r + j, 4 * r + k, 4 * r + 4 + k, 4 * r + 4 + j], 1) for r in range(3)
        ]
        quads += [np.array([[0, 3, 2, 1], [12, 13, 14, 15]])]  # outside bottom down, floor up
        q = np.concatenate(quads)
        return vertices, np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])


class PlacedGeometry(Strict):
    """Where a geometry sits in its object's frame: the data may put an object's frame at its
    base (a dish on a floor), while a primitive is centred on its own origin."""

    # bounded as a pose is: at [1e300, 0, 0] the USD export's float32 centre of mass was inf
    origin: Position = Field(
        default_factory=lambda: [0.0, 0.0, 0.0],
        description="The geometry's centre (a mesh's origin) in the object's frame, metres.",
    )


class BoxG(PlacedGeometry):
    box: BoxGeometry


class CylinderG(PlacedGeometry):
    cylinder: CylinderGeometry


class SphereG(PlacedGeometry):
    sphere: SphereGeometry


class MeshG(PlacedGeometry):
    mesh: MeshGeometry


class RevolveG(PlacedGeometry):
    revolve: RevolveGeometry


class TrayG(PlacedGeometry):
    tray: TrayGeometry


GEOMETRY_KINDS = ("box", "cylinder", "sphere", "mesh", "revolve", "tray")


def geometry_key(value: Any) -> str | None:
    """Tag of a geometry: its one shape key (`origin` beside it is not a shape).  Tags are
    "KIND-geometry", never a key of the document, so an error's location (`origin` beside the
    shape key) is not read as inside the shape's mapping."""
    if isinstance(value, BaseModel):
        keys = [k for k in GEOMETRY_KINDS if getattr(value, k, None) is not None]
    elif isinstance(value, dict):  # other keys beside one shape are reported as unknown
        keys = [k for k in value if k in GEOMETRY_KINDS]
    else:
        return None
    return f"{keys[0]}-geometry" if len(keys) == 1 else None


Geometry = Annotated[
    Union[  # noqa: UP007
        Annotated[BoxG, Tag("box-geometry")],
        Annotated[CylinderG, Tag("cylinder-geometry")],
        Annotated[SphereG, Tag("sphere-geometry")],
        Annotated[MeshG, Tag("mesh-geometry")],
        Annotated[RevolveG, Tag("revolve-geometry")],
        Annotated[TrayG, Tag("tray-geometry")],
    ],
    Discriminator(
        geometry_key,
        custom_error_type="invalid_choice",
        custom_error_message="expected a geometry: one of box, cylinder, sphere, mesh, revolve, "
        "tray (and optionally origin)",
    ),
]


class Body(Strict):
    """How a type's objects behave in simulators (docs/export.md); meaningful with geometry."""

    static: bool = Field(False, description="Welded to the world in exports; never moved.")
    mass: Positive | None = Field(None, description="Mass in kg (else from density).")
    density: Positive | None = Field(None, description="kg/m^3; default 1000 (water).")
    collision: Literal["hull", "decomposition"] | None = Field(
        None,
        description="Collision of a mesh or revolve: its convex hull, or convex pieces by coacd. "
        "Default: a revolve's exact convex pieces (its cavity stays empty), a mesh's hull.",
    )

    @model_validator(mode="after")
    def _mass_or_density(self) -> Body:
        if self.mass is not None and self.density is not None:
            raise ValueError("give mass or density, not both")
        return self


class NodeType(Strict):
    """One node type; its kind is whichever of and/or/independent/repeat it has (none: terminal)."""

    observed: bool = Field(False, description="Produces an object that appears in scenes.")
    geometry: Geometry | None = None  # type: ignore[valid-type]
    model: str | None = Field(None, description="Model file for simulators; also a dataset label.")
    body: Body | None = Field(None, description="Static or free, mass or density, collision.")
    labels: list[Annotated[str, StringConstraints(min_length=1)]] = Field(
        default_factory=list, description="Dataset class names that mean this type."
    )
    max_nesting: Annotated[int, Field(ge=1, le=100)] | None = Field(
        None, description="At most this many nodes of this type on any root-to-leaf path."
    )
    fixed: bool = Field(False, description="Keep rule probabilities / count law when fitting.")
    and_: list[Rule] | None = Field(None, alias="and", description="All rules fire.")
    or_: list[Rule] | None = Field(None, alias="or", description="Exactly one rule fires.")
    independent: list[Rule] | None = Field(None, description="Each rule fires with its own p.")
    repeat: Repeat | None = Field(None, description="One rule fires a random number of times.")

    @model_validator(mode="after")
    def _one_kind(self) -> NodeType:
        keys = ("and_", "or_", "independent", "repeat")
        kinds = [k for k in keys if getattr(self, k) is not None]
        if len(kinds) > 1:
            names = " and ".join(k.rstrip("_") for k in kinds)
            raise ValueError(f"a type has one kind of children, got {names}")
        return self


# ------------------------------------------------------------------------ constraints ---
# Scene-wide conditions the grammar itself cannot express (thesis 2.4); docs/constraints.md.
# Each constraint is a mapping with one key naming its kind.

Count_ = Annotated[int, Field(ge=0, le=1_000_000)]
Bound = Annotated[float, Field(allow_inf_nan=False)] | None


class CountC(Strict):
    """How many nodes of `type` a scene tree holds."""

    type: TypeName
    min: Count_ = 0
    max: Count_ | None = None


class ChainC(Strict):
    """The longest unbroken parent-to-child chain of nodes of a recursive `type`."""

    type: TypeName
    min: Count_ = 0
    max: Count_ | None = None


class ChildrenC(Strict):
    """How many children the nodes of type `of` produce, summed over the tree's `of` nodes."""

    of: TypeName
    child: TypeName | None = Field(None, description="Count only children of this type.")
    min: Count_ = 0
    max: Count_ | None = None


Radii = dict[TypeName, NonNegative]
TypePair = Annotated[list[TypeName], Field(min_length=2, max_length=2)]


class TailC(Strict):
    """How rare a physical finding is among the objects of real scenes, for `ssg explain`
    (docs/explain.md): P(D >= d) = rate * exp(-excess / mean).  `ssg fit` measures it."""

    rate: Annotated[float, Field(allow_inf_nan=False, gt=0, le=1)] = Field(
        description="Share of a real scene's objects (of the constraint's types) with such a "
        "finding, in (0, 1]."
    )
    mean: Annotated[float, Field(allow_inf_nan=False, gt=0)] = Field(
        description="Mean size of such a finding beyond where the tail starts (m), > 0."
    )


class InsideBoxC(Strict):
    """Every node of `types` has its origin inside a box given in a frame."""

    types: Annotated[list[TypeName], Field(min_length=1)]
    frame: TypeName | Literal["world"] = Field(
        "world", description="`world`, or a type: the nearest ancestor of that type."
    )
    min: Annotated[list[Bound], Field(min_length=3, max_length=3)] = Field(
        description="Box corner in the frame (m); null for an unbounded side."
    )
    max: Annotated[list[Bound], Field(min_length=3, max_length=3)]
    keep_out: bool = Field(
        False, description="The keep-out disc (x, y) must fit in the box too, not only the origin."
    )
    radius: Radii = Field(default_factory=dict, description="Keep-out radius per type (m).")
    geometry: bool = Field(
        False,
        description="The whole geometry (turned with the object, at its origin) must be in the "
        "box, not only the object's origin.",
    )
    floating: TailC | None = Field(
        None,
        description="With geometry: how rare objects floating more than 1 cm above the floor or "
        "what lies under them are in real scenes, and by how much beyond 1 cm (default: the "
        "sink's).",
    )
    outside: TailC | None = Field(
        None,
        description="With geometry: how rare objects going more than 1 cm through the floor or "
        "a wall are in real scenes, and by how much beyond 1 cm (default: the sink's).",
    )

    @model_validator(mode="after")
    def _one_inset(self) -> InsideBoxC:
        if self.keep_out and self.geometry:
            raise ValueError("give keep_out or geometry, not both")
        return self


class ClearanceC(Strict):
    """Horizontal (world x-y) distance between two objects >= the sum of their keep-out radii."""

    types: Annotated[list[TypeName], Field(min_length=1)]
    radius: Radii = Field(default_factory=dict, description="Keep-out radius per type (m).")
    exempt: list[TypePair] = Field(default_factory=list, description="Type pairs not checked.")
    exempt_ancestors: bool = Field(
        False, description="Do not check a node against its ancestors (stacked objects)."
    )


class UprightC(Strict):
    """An axis of each object within `max_angle_deg` of an axis of a frame."""

    types: Annotated[list[TypeName], Field(min_length=1)]
    axis: Axis = "z"
    frame: TypeName | Literal["world"] = "world"
    frame_axis: Axis = "z"
    max_angle_deg: Annotated[float, Field(allow_inf_nan=False, ge=0, le=180)]


class NonPenetrationC(Strict):
    """3-D signed distance between the geometries of two objects >= `margin`."""

    types: Annotated[list[TypeName], Field(min_length=1)]
    margin: Finite = 0.0
    exempt: list[TypePair] = Field(default_factory=list)
    exempt_ancestors: bool = False
    tail: TailC | None = Field(
        None,
        description="How rare overlapping another object the parse does not relate is in real "
        "scenes, and the mean summed overlap depth (m) (default: the sink's).",
    )


class CountSpec(Strict):
    count: CountC


class ChainSpec(Strict):
    longest_chain: ChainC


class ChildrenSpec(Strict):
    children: ChildrenC


class InsideBoxSpec(Strict):
    inside_box: InsideBoxC


class ClearanceSpec(Strict):
    clearance: ClearanceC


class UprightSpec(Strict):
    upright: UprightC


class NonPenetrationSpec(Strict):
    non_penetration: NonPenetrationC


_CHOICES["constraint"] = [
    (CountSpec, "count"),
    (ChainSpec, "longest_chain"),
    (ChildrenSpec, "children"),
    (InsideBoxSpec, "inside_box"),
    (ClearanceSpec, "clearance"),
    (UprightSpec, "upright"),
    (NonPenetrationSpec, "non_penetration"),
]
ConstraintSpec = _choice(*_CHOICES["constraint"], what="constraint")
ConstraintName = Annotated[
    str, StringConstraints(pattern=r"^[A-Za-z_][A-Za-z0-9_-]*$", max_length=200)
]


class Root(Strict):
    type: TypeName
    pose: Pose = Field(default_factory=Pose)
    required: bool = Field(
        False,
        description=(
            "Every scene shows the root object: a scene without one has no parse (default: a"
            " scene may leave an observed root out, and it is then implied at its pose)."
        ),
    )


class NoiseSpec(Strict):
    """Sensor noise of one observed type: the standard deviation of each position coordinate
    and of the rotation angle about each axis (docs/grammar.md, section 9)."""

    position: Annotated[float, Field(ge=0, le=10, allow_inf_nan=False)] = Field(
        0.0, description="Standard deviation of each position coordinate, in metres."
    )
    rotation_deg: Annotated[float, Field(ge=0, le=90, allow_inf_nan=False)] = Field(
        0.0, description="Standard deviation of the rotation about each axis, in degrees."
    )


class ClutterSpec(Strict):
    """Objects the grammar does not explain: a Poisson number per type, uniform over a box."""

    region: BoxParams = Field(description="World box where clutter objects lie.")
    rates: dict[TypeName, Annotated[float, Field(gt=0, le=100, allow_inf_nan=False)]] = Field(
        min_length=1, description="Expected number of clutter objects per scene, per type."
    )
    max: Annotated[int, Field(ge=1, le=10)] = Field(
        3, description="At most this many clutter objects in a scene."
    )


class ObservationSpec(Strict):
    """How scenes are observed: pose noise per observed type, and clutter."""

    noise: dict[TypeName, NoiseSpec] = Field(
        default_factory=dict,
        description="Per observed type (or `default` for all others): its pose noise.",
    )
    clutter: ClutterSpec | None = None


class GrammarDoc(Strict):
    """A spatial scene grammar (thesis Ch. 2.3)."""

    grammar: Annotated[str, StringConstraints(min_length=1, max_length=200)] = Field(
        description="Name of the grammar."
    )
    description: str | None = None
    root: Root | TypeName = Field(description="Root type, or {type, pose}.")
    types: dict[TypeName, NodeType] = Field(min_length=1)
    constraints: dict[ConstraintName, ConstraintSpec] = Field(  # type: ignore[valid-type]
        default_factory=dict, description="Named scene constraints (docs/constraints.md)."
    )
    observation: ObservationSpec | None = Field(
        None, description="Sensor noise and clutter (docs/grammar.md, section 9)."
    )

    @property
    def root_spec(self) -> Root:
        return self.root if isinstance(self.root, Root) else Root(type=self.root)


# ------------------------------------------------------------------- laws added later ---


def add_choice(part: str, model: Any, word: str) -> None:
    """Let a rule's `part` ("translation" or "rotation") be written `{word: ...}`, validated by
    `model`: how a law registered in `ssgc.laws` outside this module joins the language.
    With `part` "constraint", a constraint kind (`ssgc.constraints.base.register`) joins the
    `constraints:` section the same way."""
    _CHOICES[part].append((model, word))
    _rebuild(part)


def remove_choice(part: str, word: str) -> None:
    _CHOICES[part] = [(m, w) for m, w in _CHOICES[part] if w != word]
    _rebuild(part)


def _rebuild(part: str) -> None:
    """Rebuild the rule's union for `part`, then every model that holds a rule."""
    if part == "constraint":
        union = _choice(*_CHOICES[part], what="constraint")
        field = GrammarDoc.model_fields["constraints"]
        GrammarDoc.model_fields["constraints"] = FieldInfo.from_annotated_attribute(
            dict[ConstraintName, union],  # type: ignore[valid-type]
            FieldInfo.merge_field_infos(field),
        )
        GrammarDoc.model_rebuild(force=True)
        return
    union = _choice(*_CHOICES[part], what=f"{part} rule")
    Rule.model_fields[part] = FieldInfo.from_annotated_attribute(union, "same")
    for model in (Rule, Repeat, NodeType, GrammarDoc):
        model.model_rebuild(force=True)

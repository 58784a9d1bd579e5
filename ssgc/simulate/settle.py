"""Settle a scene: simulate it in MuJoCo until nothing moves, and read the poses back.

Sampled poses are only approximately physical: a plate floats a millimetre above the table,
a cup leans into a teapot.  Thesis ch. 4 simulates tables forward to static stability before
using them (objects then move a few centimetres).  The scene goes through the same MJCF
exporter as `ssg export --format mjcf` (plus a floor at z = 0), headless and on the CPU.
A scene is *settled* when every free body has been still (speed below `still_speed`, and
angular speed times 0.1 m below it, and no body speeding up `rising_chunks` chunks in a row)
for `still_time` seconds of simulated time, with its contacts seated (below) where they keep
it still, and its deepest contact is then within `max_penetration`.

Seating: the exporter's contacts (impedance 0.95) leave an object at rest about 2 µm into
its support (8 µm for a sphere's single contact point), more than the 1e-6 m within which a
pinned coordinate must match (`ssgc.laws.base.POS_TOL`), so a settled scene failed `ssg parse`
although nothing moved.  Resting penetration is (1 - d) / d * load / k for impedance d and
contact stiffness k.  Once the scene is first still, the contacts' impedance is raised to
`SEATED_IMPEDANCE` (0.999: 50 times less penetration, at the same time constant and so the
same stability at a 1 ms step); from then on stillness is counted with these contacts.  The
whole simulation is not run with them: their contacts rock a stack of trays for seconds that
the softer ones bring to rest in a fraction of one.  Where seating sets a still stack rocking
(2 of 20 unconstrained dimsum tables: a body at 1-4 cm/s), the exporter's contacts come back
for the rest of the run.
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ssgc.dsl import MAX_COORDINATE
from ssgc.errors import SsgError
from ssgc.export.bodies import SceneBodies, mesh_files
from ssgc.export.mjcf import mjcf_text
from ssgc.geometry import quat_canonical
from ssgc.io.scene import Scene, scene_to_json
from ssgc.ir import Grammar

LEVER = 0.1  # m: an angular speed counts as this lever arm times it
SEATED_IMPEDANCE = 0.999  # MuJoCo solimp d (both ends) once the scene is first still


@dataclass(frozen=True)
class SettleOptions:
    max_time: float = 5.0  # s of simulated time before giving up
    still_speed: float = 0.005  # m/s
    still_time: float = 0.2  # s
    timestep: float = 0.001  # s
    separated: float = 0.0005  # m: deepest contact left by the separation phase
    separate_steps: int = 2000
    growth_floor: float = 5e-5  # m/s: speeds below this do not count as rising
    rising_chunks: int = 3  # a body whose speed rose this many 50 ms chunks in a row is falling
    max_penetration: float = 1e-4  # m: a settled scene's deepest contact, at most

    def __post_init__(self) -> None:
        """A scene settles only after `still_time` of stillness: a shorter `max_time` could
        never settle any scene, so it is refused, not run to a certain "not settled"."""
        if not self.max_time >= self.still_time:
            raise SsgError.single(
                f"the simulated time per scene ({self.max_time:g} s) is shorter than the "
                f"{self.still_time:g} s every object must stay still to count as settled; "
                f"give at least {self.still_time:g} s"
            )


@dataclass(frozen=True)
class Settled:
    name: str
    settled: bool
    xyz: NDArray[np.float64]  # (n, 3) every body's position after settling
    quat: NDArray[np.float64]  # (n, 4)
    max_displacement: float  # m, largest distance any object moved
    penetration_before: float  # m, deepest contact before (0: none)
    penetration_after: float
    sim_time: float  # s simulated
    wall_time: float  # s
    unstable: bool = False  # MuJoCo found the simulation unstable and reset it
    reason: str = ""  # why it is not settled ("" when it is)

    def report(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "settled": self.settled,
            "reason": self.reason,
            "max_displacement": self.max_displacement,
            "penetration_before": self.penetration_before,
            "penetration_after": self.penetration_after,
            "sim_time": round(self.sim_time, 6),
            "wall_time": round(self.wall_time, 6),
            "unstable": self.unstable,
        }


def require_mujoco():  # type: ignore[no-untyped-def]
    try:
        import mujoco
    except ImportError:
        raise SsgError.single("settling needs MuJoCo: pip install 'ssgc[sim]'") from None
    return mujoco


def build_model(scene: SceneBodies, timestep: float = 0.001):  # type: ignore[no-untyped-def]
    """The scene's MuJoCo model (with a floor), through the MJCF exporter."""
    mujoco = require_mujoco()
    with tempfile.TemporaryDirectory(prefix="ssgc-settle-") as tmp:
        for rel, text in mesh_files(scene, "meshes").items():
            (Path(tmp) / rel).parent.mkdir(parents=True, exist_ok=True)
            (Path(tmp) / rel).write_text(text, encoding="utf-8")
        xml = Path(tmp) / "scene.xml"
        xml.write_text(mjcf_text(scene, "meshes", floor=True, timestep=timestep), "utf-8")
        try:
            return mujoco.MjModel.from_xml_path(str(xml))
        except ValueError as exc:  # e.g. a mass below MuJoCo's smallest (a grammar's numbers)
            reason = " ".join(str(exc).split())
            raise SsgError.single(
                f"scene '{scene.name}': MuJoCo cannot load it: {reason}"
            ) from None


def penetration(model, data) -> float:  # type: ignore[no-untyped-def]
    """The deepest contact of the current state, in meters (0 when nothing touches)."""
    require_mujoco().mj_forward(model, data)
    if data.ncon == 0:
        return 0.0
    return float(max(0.0, -np.min(data.contact.dist[: data.ncon])))


def settle_scene(scene: SceneBodies, options: SettleOptions | None = None) -> Settled:
    """Simulate until still, with MuJoCo's warnings kept out of the user's terminal (and out
    of the MUJOCO_LOG.TXT it would write in the current directory): an unstable simulation
    is what `Settled.unstable` says."""
    mujoco = require_mujoco()
    previous = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(lambda message: None)  # the data's warning counts tell
    try:
        return _settle(mujoco, scene, options or SettleOptions())
    finally:
        mujoco.set_mju_user_warning(previous)


def _settle(mujoco, scene: SceneBodies, options: SettleOptions) -> Settled:  # type: ignore[no-untyped-def]
    start = time.perf_counter()
    model = build_model(scene, options.timestep)
    data = mujoco.MjData(model)
    before = penetration(model, data)
    ids = [model.body(b.name).id for b in scene.bodies]
    xyz0 = data.xpos[ids].copy()
    free = model.jnt_type == mujoco.mjtJoint.mjJNT_FREE
    if not free.any():
        return _nothing_moves(scene, before, start)
    dofs = model.jnt_dofadr[free][:, None] + np.arange(6)  # (bodies, 6): linear, angular
    _separate(mujoco, model, data, options)
    data.time = 0.0
    chunk = max(1, round(0.05 / options.timestep))
    still = 0.0  # simulated time is counted here: MuJoCo resets data.time when unstable
    steps = max(1, round(options.max_time / options.timestep))  # --max-time is at most
    done = 0
    speed = np.zeros(len(dofs))  # the separation phase leaves every body at rest
    rises = np.zeros(len(dofs), np.int64)  # chunks in a row each body has sped up
    exporters = model.geom_solimp.copy()
    seated = watched = False  # watched: first still, from then on a rising body is falling
    while done < steps and still < options.still_time:
        n = min(chunk, steps - done)
        mujoco.mj_step(model, data, nstep=n)
        done += n
        previous, speed = speed, body_speeds(data.qvel[dofs])
        rises = np.where(speed > np.maximum(previous, options.growth_floor), rises + 1, 0)
        calm = is_still(speed, rises, watched, options)
        still = still + n * options.timestep if calm else 0.0
        if calm and not watched:
            seat_contacts(model)
            seated = watched = True
        elif seated and not np.all(speed < options.still_speed):
            # the seated contacts set a stack rocking (cm/s): back to the exporter's, with
            # which it was still, for good (it then rests ~2 µm deep, not ~0.04 µm)
            model.geom_solimp[:] = exporters
            seated = False
    simulated = done * options.timestep
    after = penetration(model, data)
    xyz = data.xpos[ids].copy()
    quat = quat_canonical(data.xquat[ids].copy())
    bad = int(data.warning[mujoco.mjtWarning.mjWARN_BADQACC].number) > 0
    bad |= not (np.isfinite(xyz).all() and np.isfinite(quat).all())
    far = not bad and not np.all(np.abs(xyz) <= MAX_COORDINATE)  # beyond every scene reader
    bad |= far
    if bad:
        # MuJoCo reset an unstable simulation (objects far apart in scale, absurd poses), or
        # it flung an object beyond the 1,000 km a scene file may hold (a box 100 km wide
        # on the floor): keep the scene as it was and say it did not settle.
        xyz, after, still = xyz0, before, 0.0
        quat = np.array([b.quat for b in scene.bodies]).reshape(-1, 4)
    reason = _unsettled_reason(bad, still >= options.still_time, after, options)
    if far:
        reason = (
            f"an object left the {MAX_COORDINATE / 1000:,.0f} km from the origin that scene "
            "files hold (the simulation went unstable), poses kept"
        )
    return Settled(
        scene.name,
        not reason,
        xyz,
        quat,
        float(np.max(np.linalg.norm(xyz - xyz0, axis=1), initial=0.0)),
        before,
        after,
        simulated,
        time.perf_counter() - start,
        unstable=bad,
        reason=reason,
    )


def body_speeds(qvel: NDArray[np.float64]) -> NDArray[np.float64]:
    """Each free body's speed from its (6,) velocities: the largest linear component, or the
    largest angular one times `LEVER`, whichever is larger."""
    return np.maximum(
        np.max(np.abs(qvel[:, :3]), axis=1), LEVER * np.max(np.abs(qvel[:, 3:]), axis=1)
    )


def is_still(
    speed: NDArray[np.float64],
    rises: NDArray[np.int64],
    watched: bool,
    options: SettleOptions,
) -> bool:
    """Whether a chunk of simulation counts toward the still time: every body slower than
    `still_speed` and, once the scene has been still (`watched`), none sped up
    `rising_chunks` chunks in a row (beyond `growth_floor`).  Speed alone is not enough: the
    simulation starts from rest, so a pole standing just past its balance point is slow for
    its first 0.2 s, and was reported settled although it was starting to fall; a falling
    body speeds up chunk after chunk.  A body at rest jitters instead: seated stacks of
    trays at 1-3 mm/s, faster in one chunk and slower in the next, so a single rise is not a
    fall (requiring none left 8 of 20 unconstrained dimsum tables unsettled after 30 s)."""
    slow = bool(np.all(speed < options.still_speed))
    if not watched:
        return slow
    return slow and bool(np.all(rises < options.rising_chunks))


def seat_contacts(model) -> None:  # type: ignore[no-untyped-def]
    """Raise every contact's impedance to `SEATED_IMPEDANCE` (module docstring, "Seating"):
    resting objects then sink 50 times less into their supports, well within the 1e-6 m of a
    pinned coordinate.  Geoms without contacts (the visual ones) are unaffected."""
    model.geom_solimp[:, :2] = SEATED_IMPEDANCE


def _unsettled_reason(bad: bool, still: bool, after: float, options: SettleOptions) -> str:
    """Why a scene is not settled, in the words of its report line ("" when it is).

    A still scene can still be far from rest as the docs promise it: a 10 kg box on a 1 g
    one stands still 3.9 mm inside it (a contact holds it only as deep as its load is large
    against its own weight).  Such a scene is not settled."""
    if bad:
        return "the simulation went unstable (MuJoCo reset it), poses kept"
    if not still:
        return "did not come to rest"
    if after > options.max_penetration:
        return (
            f"it came to rest {1000 * after:.3f} mm deep in a contact, deeper than the "
            f"{1000 * options.max_penetration:g} mm a settled scene may be"
        )
    return ""


def _nothing_moves(scene: SceneBodies, penetration: float, start: float) -> Settled:
    """A scene without a free body (no object, or fixed ones only) is settled as it is, its
    poses unchanged: there is nothing to wait for (with a short `max_time` such a scene was
    reported "not settled")."""
    xyz = np.array([b.xyz for b in scene.bodies], dtype=float).reshape(-1, 3)
    quat = np.array([b.quat for b in scene.bodies], dtype=float).reshape(-1, 4)
    wall = time.perf_counter() - start
    return Settled(scene.name, True, xyz, quat, 0.0, penetration, penetration, 0.0, wall)


def _separate(mujoco, model, data, options: SettleOptions) -> None:  # type: ignore[no-untyped-def]
    """Push interpenetrating objects apart before the real simulation starts.

    A sampled scene can have a cup half inside a teapot; simulated as it is, the contact
    force launches the cup across the room.  So first, without gravity, every step's
    velocity is thrown away: each step moves the objects a little along the contact forces,
    a projection onto non-penetration rather than an explosion.  It stops once the deepest
    contact is under `options.separated` (or after `options.separate_steps` steps).
    """
    gravity = model.opt.gravity.copy()
    model.opt.gravity[:] = 0.0
    try:
        for step in range(options.separate_steps):
            if step % 10 == 0 and penetration(model, data) <= options.separated:
                break
            mujoco.mj_step(model, data)
            data.qvel[:] = 0.0
    finally:
        model.opt.gravity[:] = gravity
        data.qvel[:] = 0.0


def provenance(result: Settled, source: dict[str, Any]) -> dict[str, Any]:
    """What a settled scene file records about how it was made: everything of the report but
    the wall-clock time, which differs from run to run, so that the same command writes the
    same files (docs/scenes.md; the time stays in `--report`)."""
    mujoco = require_mujoco()
    return {
        "engine": "mujoco",
        "engine_version": mujoco.__version__,
        **{k: v for k, v in source.items() if v is not None},
        **{k: v for k, v in result.report().items() if k not in ("name", "wall_time")},
    }


def settled_scene_json(
    grammar: Grammar, scene: Scene, result: Settled, source: dict[str, Any]
) -> dict[str, Any]:
    """The settled scene in the scene format: the same objects at their new poses.

    The tree and log-probability are dropped (they describe the poses before settling); the
    scene's `metadata.settle` records the engine, the source and the report.
    """
    moved = Scene(scene.name, scene.types, result.xyz, result.quat, scene.metadata)
    return scene_to_json(
        grammar, moved, metadata={**scene.extra, "settle": provenance(result, source)}
    )


def settle_summary(reports: list[dict[str, Any]]) -> dict[str, Any]:
    """A run's figures from its scenes' reports (`Settled.report`): how many settled, how far
    things moved, how deep they still overlap, how long it took."""
    moved = np.array([r["max_displacement"] for r in reports])
    return {
        "scenes": len(reports),
        "settled": sum(r["settled"] for r in reports),
        "median_displacement": float(np.median(moved)) if len(moved) else 0.0,
        "max_displacement": float(moved.max(initial=0.0)),
        "max_penetration_after": max((r["penetration_after"] for r in reports), default=0.0),
        "mean_wall_time": float(np.mean([r["wall_time"] for r in reports])) if reports else 0.0,
    }

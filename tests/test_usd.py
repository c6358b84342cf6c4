"""Tests for warpdem.io.usd: the written stage is read back with pxr and compared with the input.

Tolerances: positions, velocities, widths and colours are stored as float32, so values are compared with a
relative tolerance of 1e-6 (float32 epsilon is 1.2e-7); times are stored as double and compared exactly.
"""

from __future__ import annotations

import pathlib

import numpy as np
import pytest
from pxr import Usd, UsdGeom

from warpdem.io.usd import CurveSet, SurfaceFrame, UsdWriter

RTOL = 1e-6  # float32 storage
FPS = 24.0


def make_frames(seed: int = 0) -> list[dict[str, np.ndarray | float]]:
    """Three frames with 4, 4 and 3 particles; the third drops the particle with id 11."""
    rng = np.random.default_rng(seed)
    frames = []
    ids_per_frame = [np.array([10, 11, 12, 13]), np.array([10, 11, 12, 13]), np.array([10, 12, 13])]
    for k, ids in enumerate(ids_per_frame):
        n = ids.size
        frames.append(
            {
                "time": 1.0e-3 * (k + 1) + 1.0e-9,  # not a multiple of 1/FPS: time codes must not derive from it
                "positions": rng.normal(size=(n, 3)),
                "radii": rng.uniform(0.01, 0.05, size=n),
                "velocities": rng.normal(size=(n, 3)),
                "ids": ids.astype(np.int64),
                "colors": rng.uniform(0.0, 1.0, size=(n, 3)),
            }
        )
    return frames


def test_round_trip(tmp_path: pathlib.Path) -> None:
    final = tmp_path / "out" / "run.usdc"
    frames = make_frames()
    writer = UsdWriter(final, FPS, comment="unit test")
    partial = tmp_path / "out" / "run.partial.usdc"
    assert writer.partial_path == partial.resolve()
    codes = [writer.write_frame(**frame) for frame in frames]
    assert codes == [0, 1, 2]
    assert writer.frame_count == 3
    assert not final.exists()
    assert writer.close() == final.resolve()
    assert final.exists()
    assert not partial.exists()

    stage = Usd.Stage.Open(str(final))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetTimeCodesPerSecond() == FPS
    assert stage.GetFramesPerSecond() == FPS
    assert stage.GetStartTimeCode() == 0.0
    assert stage.GetEndTimeCode() == 2.0
    assert stage.GetDefaultPrim().GetPath() == "/World"
    assert stage.GetRootLayer().comment == "unit test"
    assert stage.GetRootLayer().GetFileFormat().formatId == "usdc"

    world = stage.GetPrimAtPath("/World")
    time_attr = world.GetAttribute("warpdem:time")
    assert time_attr.IsCustom()
    assert time_attr.GetTimeSamples() == [0.0, 1.0, 2.0]
    for code, frame in enumerate(frames):
        assert time_attr.Get(code) == frame["time"]

    points = UsdGeom.Points(stage.GetPrimAtPath("/World/Particles"))
    assert points
    assert points.GetPointsAttr().GetTimeSamples() == [0.0, 1.0, 2.0]
    assert points.GetIdsAttr().GetTimeSamples() == [0.0, 2.0]
    assert points.GetWidthsInterpolation() == UsdGeom.Tokens.vertex
    color = points.GetDisplayColorPrimvar()
    speed = UsdGeom.PrimvarsAPI(points.GetPrim()).GetPrimvar("speed")
    assert color.GetInterpolation() == UsdGeom.Tokens.vertex
    assert speed.GetInterpolation() == UsdGeom.Tokens.vertex
    assert not stage.GetPrimAtPath("/World/Bonds")

    for code, frame in enumerate(frames):
        pos = np.asarray(points.GetPointsAttr().Get(code))
        widths = np.asarray(points.GetWidthsAttr().Get(code))
        vel = np.asarray(points.GetVelocitiesAttr().Get(code))
        np.testing.assert_allclose(pos, frame["positions"], rtol=RTOL, atol=1e-7)
        np.testing.assert_allclose(widths, 2.0 * frame["radii"], rtol=RTOL)
        np.testing.assert_allclose(vel, frame["velocities"], rtol=RTOL, atol=1e-7)
        # ids are held between authored samples, so every frame reads back its own list.
        np.testing.assert_array_equal(np.asarray(points.GetIdsAttr().Get(code)), frame["ids"])
        np.testing.assert_allclose(np.asarray(color.Get(code)), frame["colors"], rtol=RTOL, atol=1e-7)
        np.testing.assert_allclose(
            np.asarray(speed.Get(code)), np.linalg.norm(frame["velocities"], axis=1), rtol=RTOL, atol=1e-7
        )
        extent = np.asarray(points.GetExtentAttr().Get(code))
        r = frame["radii"][:, None]
        np.testing.assert_allclose(extent[0], (frame["positions"] - r).min(axis=0), rtol=RTOL, atol=1e-7)
        np.testing.assert_allclose(extent[1], (frame["positions"] + r).max(axis=0), rtol=RTOL, atol=1e-7)


def test_bonds(tmp_path: pathlib.Path) -> None:
    final = tmp_path / "bonds.usda"
    frames = make_frames(seed=1)
    bonds = [np.array([[0, 1], [2, 3]]), np.zeros((0, 2), dtype=np.int32), np.array([[0, 2]])]
    with UsdWriter(final, FPS) as writer:
        for frame, frame_bonds in zip(frames, bonds, strict=True):
            writer.write_frame(**frame, bonds=frame_bonds)
    assert (tmp_path / "bonds.usda").exists()
    assert not (tmp_path / "bonds.partial.usda").exists()

    stage = Usd.Stage.Open(str(final))
    assert stage.GetRootLayer().GetFileFormat().formatId == "usda"
    curves = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/Bonds"))
    assert curves
    assert curves.GetTypeAttr().Get() == UsdGeom.Tokens.linear
    assert curves.GetWidthsInterpolation() == UsdGeom.Tokens.constant
    assert curves.GetPointsAttr().GetTimeSamples() == [0.0, 1.0, 2.0]
    for code, (frame, frame_bonds) in enumerate(zip(frames, bonds, strict=True)):
        pts = np.asarray(curves.GetPointsAttr().Get(code)).reshape(-1, 3)
        counts = np.asarray(curves.GetCurveVertexCountsAttr().Get(code))
        widths = np.asarray(curves.GetWidthsAttr().Get(code))
        expected = frame["positions"][frame_bonds.reshape(-1)]
        np.testing.assert_allclose(pts, expected, rtol=RTOL, atol=1e-7)
        np.testing.assert_array_equal(counts, np.full(len(frame_bonds), 2))
        np.testing.assert_allclose(widths, [0.5 * frame["radii"].mean()], rtol=RTOL)


def test_bonds_appear_late(tmp_path: pathlib.Path) -> None:
    """Frames before the first bonds read back as no bonds, and frames that omit bonds draw none."""
    final = tmp_path / "late.usdc"
    frames = make_frames(seed=2)
    with UsdWriter(final, FPS) as writer:
        writer.write_frame(**frames[0])
        writer.write_frame(**frames[1], bonds=np.array([[0, 3]]))
        writer.write_frame(**frames[2])
    stage = Usd.Stage.Open(str(final))  # prims do not keep their stage alive
    curves = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/Bonds"))
    assert len(curves.GetCurveVertexCountsAttr().Get(0)) == 0
    assert len(curves.GetCurveVertexCountsAttr().Get(1)) == 1
    assert len(curves.GetCurveVertexCountsAttr().Get(2)) == 0


def test_periodic_save(tmp_path: pathlib.Path) -> None:
    """Saving the crate file mid-run must not lose or corrupt samples authored before or after."""
    final = tmp_path / "periodic.usd"
    frames = make_frames(seed=3) * 3
    writer = UsdWriter(final, FPS)
    writer.save_interval_frames = 2
    for frame in frames:
        writer.write_frame(**frame)
    assert writer.partial_path.exists()
    writer.close()
    assert final.read_bytes()[:8] == b"PXR-USDC"  # ".usd" is written as binary crate
    stage = Usd.Stage.Open(str(final))
    assert stage.GetEndTimeCode() == len(frames) - 1
    points = UsdGeom.Points(stage.GetPrimAtPath("/World/Particles"))
    for code, frame in enumerate(frames):
        np.testing.assert_allclose(
            np.asarray(points.GetPointsAttr().Get(code)), frame["positions"], rtol=RTOL, atol=1e-7
        )
    assert points.GetIdsAttr().GetTimeSamples() == [0.0, 2.0, 3.0, 5.0, 6.0, 8.0]


def test_abort_leaves_no_file(tmp_path: pathlib.Path) -> None:
    final = tmp_path / "aborted.usdc"
    writer = UsdWriter(final, FPS)
    writer.write_frame(**make_frames()[0])
    assert writer.partial_path.exists()
    writer.abort()
    assert list(tmp_path.iterdir()) == []
    writer.abort()  # idempotent
    with pytest.raises(RuntimeError, match="closed"):
        writer.write_frame(**make_frames()[0])


def test_abort_keeps_previous_output(tmp_path: pathlib.Path) -> None:
    final = tmp_path / "keep.usdc"
    with UsdWriter(final, FPS) as writer:
        writer.write_frame(**make_frames()[0])
    before = final.read_bytes()
    writer = UsdWriter(final, FPS)
    writer.write_frame(**make_frames()[1])
    writer.abort()
    assert final.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.usdc"]


def test_context_manager_aborts_on_exception(tmp_path: pathlib.Path) -> None:
    final = tmp_path / "ctx.usdc"
    with pytest.raises(KeyError), UsdWriter(final, FPS) as writer:
        writer.write_frame(**make_frames()[0])
        raise KeyError("simulated failure")
    assert not final.exists()
    assert not writer.partial_path.exists()


def test_stale_partial_is_replaced(tmp_path: pathlib.Path) -> None:
    (tmp_path / "stale.partial.usdc").write_bytes(b"left over from a crash")
    with UsdWriter(tmp_path / "stale.usdc", FPS) as writer:
        writer.write_frame(**make_frames()[0])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["stale.usdc"]


@pytest.mark.parametrize("name", ["run.abc", "run", "run.usdz", "run.h5"])
def test_bad_suffix(tmp_path: pathlib.Path, name: str) -> None:
    with pytest.raises(ValueError, match="unsupported suffix"):
        UsdWriter(tmp_path / name, FPS)
    assert list(tmp_path.iterdir()) == []


def test_bad_inputs(tmp_path: pathlib.Path) -> None:
    with pytest.raises(ValueError, match="frames_per_second"):
        UsdWriter(tmp_path / "x.usda", 0.0)
    frame = make_frames()[0]
    with UsdWriter(tmp_path / "x.usda", FPS) as writer:
        with pytest.raises(ValueError, match="radii"):
            writer.write_frame(**{**frame, "radii": frame["radii"][:2]})
        with pytest.raises(ValueError, match="ids"):
            writer.write_frame(**{**frame, "ids": frame["ids"].astype(np.float64)})
        with pytest.raises(ValueError, match="bonds"):
            writer.write_frame(**frame, bonds=np.array([[0, 4]]))
        assert writer.frame_count == 0


def test_first_frame_offsets_the_timeline(tmp_path: pathlib.Path) -> None:
    """A restarted run continues the original timeline: codes first_frame, first_frame + 1, ... and the stage's
    start/end time codes say so."""
    frames = make_frames()
    path = tmp_path / "restart.usdc"
    with UsdWriter(path, 25.0, first_frame=7) as writer:
        codes = [writer.write_frame(**f) for f in frames[:2]]
    assert codes == [7, 8]
    stage = Usd.Stage.Open(str(path))
    assert stage.GetStartTimeCode() == 7.0
    assert stage.GetEndTimeCode() == 8.0
    points = UsdGeom.Points.Get(stage, "/World/Particles").GetPointsAttr()
    assert points.GetTimeSamples() == [7.0, 8.0]
    # Stored as float32 (Vec3f): equal to the input rounded to float32, bit for bit.
    np.testing.assert_array_equal(np.asarray(points.Get(8.0)), np.asarray(frames[1]["positions"], dtype=np.float32))


# ----------------------------------------------------------------------------------------------------------------
# Rock surface (/World/Rock)


def make_surface(
    points: np.ndarray, faces: np.ndarray, seed: int, vertex_colors: bool = False, damage: bool = False
) -> SurfaceFrame:
    rng = np.random.default_rng(seed)
    f, p = len(faces), len(points)
    return SurfaceFrame(
        points=points,
        faces=faces,
        velocities=rng.normal(size=(p, 3)),
        von_mises=rng.uniform(0.0, 1e6, size=f),
        max_principal=rng.normal(scale=1e6, size=f),
        colors=rng.uniform(0.0, 1.0, size=(p if vertex_colors else f, 3)),
        vertex_colors=vertex_colors,
        damage=rng.uniform(0.0, 1.0, size=p) if damage else None,
    )


def make_curves(count: int, seed: int) -> CurveSet:
    rng = np.random.default_rng(seed)
    return CurveSet(
        endpoints=rng.normal(size=(count, 2, 3)),
        width=0.01 * (seed + 1),
        damage=rng.uniform(0.0, 1.0, size=count),
        colors=rng.uniform(0.0, 1.0, size=(count, 3)),
    )


TETRA_POINTS = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [5.0, 5.0, 5.0]])
TETRA_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])  # outward faces; point 4 is unused


def test_rock_surface_time_samples_and_topology_only_on_change(tmp_path: pathlib.Path) -> None:
    """Points, velocities, primvars and extent are sampled every frame; the topology only at frames 0 and 2, where it
    changes; frame 3 repeats frame 2's topology and authors none."""
    frames = make_frames()
    frames.append(make_frames(seed=4)[2])
    shift = np.array([0.0, 0.0, 0.5])
    faces_per_frame = [TETRA_FACES, TETRA_FACES, TETRA_FACES[:3], TETRA_FACES[:3].copy()]
    surfaces = [make_surface(TETRA_POINTS + k * shift, faces, seed=k) for k, faces in enumerate(faces_per_frame)]
    path = tmp_path / "rock.usda"
    with UsdWriter(path, FPS) as writer:
        for frame, surface in zip(frames, surfaces, strict=True):
            writer.write_frame(**frame, surface=surface)

    stage = Usd.Stage.Open(str(path))
    rock = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Rock"))
    assert rock
    assert rock.GetSubdivisionSchemeAttr().Get() == UsdGeom.Tokens.none
    every = [0.0, 1.0, 2.0, 3.0]
    assert rock.GetPointsAttr().GetTimeSamples() == every
    assert rock.GetVelocitiesAttr().GetTimeSamples() == every
    assert rock.GetExtentAttr().GetTimeSamples() == every
    assert rock.GetFaceVertexIndicesAttr().GetTimeSamples() == [0.0, 2.0]
    assert rock.GetFaceVertexCountsAttr().GetTimeSamples() == [0.0, 2.0]
    primvars = UsdGeom.PrimvarsAPI(rock.GetPrim())
    speed = primvars.GetPrimvar("speed")
    von_mises = primvars.GetPrimvar("vonMisesStress")
    max_principal = primvars.GetPrimvar("maxPrincipalStress")
    color = rock.GetDisplayColorPrimvar()
    assert speed.GetInterpolation() == UsdGeom.Tokens.vertex
    assert von_mises.GetInterpolation() == UsdGeom.Tokens.uniform
    assert max_principal.GetInterpolation() == UsdGeom.Tokens.uniform
    assert color.GetInterpolation() == UsdGeom.Tokens.uniform
    for name in ("speed", "vonMisesStress", "maxPrincipalStress", "displayColor"):
        assert primvars.GetPrimvar(name).GetAttr().GetTimeSamples() == every, name

    for code, (surface, faces) in enumerate(zip(surfaces, faces_per_frame, strict=True)):
        np.testing.assert_allclose(np.asarray(rock.GetPointsAttr().Get(code)), surface.points, rtol=RTOL, atol=1e-7)
        # Topology is held between authored samples: every frame reads back its own triangles.
        np.testing.assert_array_equal(np.asarray(rock.GetFaceVertexIndicesAttr().Get(code)), faces.reshape(-1))
        np.testing.assert_array_equal(np.asarray(rock.GetFaceVertexCountsAttr().Get(code)), np.full(len(faces), 3))
        np.testing.assert_allclose(
            np.asarray(speed.Get(code)), np.linalg.norm(surface.velocities, axis=1), rtol=RTOL, atol=1e-7
        )
        np.testing.assert_allclose(np.asarray(von_mises.Get(code)), surface.von_mises, rtol=RTOL)
        np.testing.assert_allclose(np.asarray(max_principal.Get(code)), surface.max_principal, rtol=RTOL)
        np.testing.assert_allclose(np.asarray(color.Get(code)), surface.colors, rtol=RTOL, atol=1e-7)
        # The extent bounds the triangles' vertices only: the unused point 4 lies outside it.
        extent = np.asarray(rock.GetExtentAttr().Get(code))
        np.testing.assert_allclose(extent, [code * shift, code * shift + 1.0], rtol=RTOL, atol=1e-7)


def test_rock_surface_vertex_colors_and_late_appearance(tmp_path: pathlib.Path) -> None:
    """A surface first given at frame 1 reads back empty at frame 0; a frame without one authors an empty mesh."""
    frames = make_frames()
    path = tmp_path / "late_rock.usdc"
    surface = make_surface(TETRA_POINTS, TETRA_FACES, seed=0, vertex_colors=True)
    with UsdWriter(path, FPS) as writer:
        writer.write_frame(**frames[0])
        writer.write_frame(**frames[1], surface=surface)
        writer.write_frame(**frames[2])
    stage = Usd.Stage.Open(str(path))
    rock = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Rock"))
    assert rock.GetDisplayColorPrimvar().GetInterpolation() == UsdGeom.Tokens.vertex
    counts = rock.GetFaceVertexCountsAttr()
    assert [len(counts.Get(c)) for c in (0.0, 1.0, 2.0)] == [0, 4, 0]
    np.testing.assert_allclose(np.asarray(rock.GetDisplayColorPrimvar().Get(1.0)), surface.colors, rtol=RTOL)


def test_rock_damage_primvar_and_cohesive_curves(tmp_path: pathlib.Path) -> None:
    """primvars:damage on /World/Rock (vertex) reads back at every frame; /World/Cohesive appears at frame 1 (empty at
    frame 0), one 2-point curve per element with its ends, width, damage and colour, and is emptied at frame 3."""
    frames = [*make_frames(), make_frames(seed=3)[0]]
    surfaces = [make_surface(TETRA_POINTS + 0.1 * k, TETRA_FACES, seed=k, damage=True) for k in range(4)]
    curves = [None, make_curves(3, seed=1), make_curves(2, seed=2), None]
    path = tmp_path / "cracks.usdc"
    with UsdWriter(path, FPS) as writer:
        for frame, surface, cohesive in zip(frames, surfaces, curves, strict=True):
            writer.write_frame(**frame, surface=surface, cohesive=cohesive)
    stage = Usd.Stage.Open(str(path))
    damage = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/World/Rock")).GetPrimvar("damage")
    assert damage.GetInterpolation() == UsdGeom.Tokens.vertex
    assert damage.GetAttr().GetTimeSamples() == [0.0, 1.0, 2.0, 3.0]
    for code, surface in enumerate(surfaces):
        np.testing.assert_array_equal(np.asarray(damage.Get(code)), surface.damage.astype(np.float32))
    cohesive = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/Cohesive"))
    assert cohesive.GetTypeAttr().Get() == UsdGeom.Tokens.linear
    primvars = UsdGeom.PrimvarsAPI(cohesive.GetPrim())
    assert primvars.GetPrimvar("damage").GetInterpolation() == UsdGeom.Tokens.uniform
    assert cohesive.GetDisplayColorPrimvar().GetInterpolation() == UsdGeom.Tokens.uniform
    for code, c in enumerate(curves):
        m = 0 if c is None else len(c.endpoints)
        np.testing.assert_array_equal(np.asarray(cohesive.GetCurveVertexCountsAttr().Get(code)), np.full(m, 2))
        points = np.asarray(cohesive.GetPointsAttr().Get(code)).reshape(m, 2, 3)
        if c is None:
            continue
        np.testing.assert_array_equal(points, c.endpoints.astype(np.float32))
        np.testing.assert_allclose(np.asarray(cohesive.GetWidthsAttr().Get(code)), [c.width], rtol=RTOL)
        np.testing.assert_array_equal(np.asarray(primvars.GetPrimvar("damage").Get(code)), c.damage.astype(np.float32))
        np.testing.assert_array_equal(
            np.asarray(cohesive.GetDisplayColorPrimvar().Get(code)), c.colors.astype(np.float32)
        )
        extent = np.asarray(cohesive.GetExtentAttr().Get(code))
        ends = c.endpoints.reshape(-1, 3).astype(np.float32)
        half = 0.5 * np.float32(c.width)
        np.testing.assert_allclose(extent, [ends.min(axis=0) - half, ends.max(axis=0) + half], rtol=RTOL)


def test_rock_surface_bad_inputs(tmp_path: pathlib.Path) -> None:
    frame = make_frames()[0]
    good = make_surface(TETRA_POINTS, TETRA_FACES, seed=0)
    with UsdWriter(tmp_path / "bad.usda", FPS) as writer:
        with pytest.raises(ValueError, match=r"surface\.faces"):
            writer.write_frame(**frame, surface=make_surface(TETRA_POINTS, TETRA_FACES + 4, seed=0))
        with pytest.raises(ValueError, match=r"surface\.faces"):
            writer.write_frame(**frame, surface=make_surface(TETRA_POINTS, TETRA_FACES.astype(float), seed=0))
        with pytest.raises(ValueError, match=r"surface\.von_mises"):
            writer.write_frame(**frame, surface=SurfaceFrame(**{**vars(good), "von_mises": good.von_mises[:2]}))
        with pytest.raises(ValueError, match=r"surface\.colors"):
            writer.write_frame(**frame, surface=SurfaceFrame(**{**vars(good), "vertex_colors": True}))
        with pytest.raises(ValueError, match=r"surface\.damage"):
            writer.write_frame(**frame, surface=SurfaceFrame(**{**vars(good), "damage": np.zeros(2)}))
        curves = make_curves(2, seed=0)
        with pytest.raises(ValueError, match=r"cohesive\.endpoints"):
            writer.write_frame(**frame, cohesive=CurveSet(**{**vars(curves), "endpoints": np.zeros((2, 3))}))
        with pytest.raises(ValueError, match=r"cohesive\.damage"):
            writer.write_frame(**frame, cohesive=CurveSet(**{**vars(curves), "damage": np.zeros(3)}))
        with pytest.raises(ValueError, match=r"cohesive\.width"):
            writer.write_frame(**frame, cohesive=CurveSet(**{**vars(curves), "width": float("nan")}))
        assert writer.frame_count == 0


# ----------------------------------------------------------------------------------------------------------------
# A restart extends the stage (append=True): oracle, the stage written in one go, sample by sample


def story() -> list[dict]:
    """Six frames in which everything a frame can change changes: no spheres at first (frames 0–1), spheres from
    frame 2 with ids changing at 4, bonds from 3, a rock surface with damage from 1 whose triangles change at 3 and
    vanish at 5, cohesive curves from 2 that vanish at 5."""
    base = make_frames() + make_frames(seed=2)
    none = {
        "positions": np.zeros((0, 3)),
        "radii": np.zeros(0),
        "velocities": np.zeros((0, 3)),
        "ids": np.zeros(0, np.int64),
        "colors": np.zeros((0, 3)),
    }
    frames = []
    for k in range(6):
        frame = {**base[k], **(none if k < 2 else {}), "time": 0.01 * k}
        if k >= 3:
            frame["bonds"] = np.array([[0, 1]])
        if 1 <= k < 5:
            faces = TETRA_FACES if k < 3 else TETRA_FACES[:2]
            frame["surface"] = make_surface(TETRA_POINTS + 0.1 * k, faces, seed=k, damage=True)
        if 2 <= k < 5:
            frame["cohesive"] = make_curves(k, seed=k)
        frames.append(frame)
    return frames


@pytest.mark.parametrize("restart_frame", range(6))
@pytest.mark.parametrize("suffix", [".usdc", ".usda"])
def test_append_continues_the_animation(tmp_path: pathlib.Path, restart_frame: int, suffix: str) -> None:
    """Frames 0..5 in one go, and a stage of frames 0..5 rewritten from ``restart_frame`` on by a second writer: equal
    stages, sample by sample (what a restart from that frame's checkpoint does to the published stage)."""
    from stage_compare import assert_stages_equal

    frames = story()
    whole, pieces = tmp_path / f"whole{suffix}", tmp_path / f"pieces{suffix}"
    with UsdWriter(whole, FPS) as writer:
        for frame in frames:
            writer.write_frame(**frame)
    with UsdWriter(pieces, FPS) as writer:
        # The first run: its frames from restart_frame on differ (moved by 1 m), and must all be replaced.
        for k, frame in enumerate(frames):
            writer.write_frame(**{**frame, "positions": frame["positions"] + (k >= restart_frame)})
    with UsdWriter(pieces, FPS, first_frame=restart_frame, append=True) as writer:
        assert writer.extended
        for frame in frames[restart_frame:]:
            writer.write_frame(**frame)
    assert_stages_equal(Usd.Stage.Open(str(pieces)), Usd.Stage.Open(str(whole)))
    assert not list(tmp_path.glob("*.partial*"))


def test_append_without_a_stage_starts_at_the_restart_frame(tmp_path: pathlib.Path) -> None:
    path = tmp_path / "new.usdc"
    with UsdWriter(path, FPS, first_frame=4, append=True) as writer:
        assert not writer.extended
        writer.write_frame(**make_frames()[0])
    stage = Usd.Stage.Open(str(path))
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (4.0, 4.0)


def test_append_at_another_frame_rate_is_refused_and_keeps_the_stage(tmp_path: pathlib.Path) -> None:
    path = tmp_path / "run.usdc"
    with UsdWriter(path, FPS) as writer:
        writer.write_frame(**make_frames()[0])
    before = path.read_bytes()
    with pytest.raises(ValueError, match="frame rate is 24 frames/s, this run's 25"):
        UsdWriter(path, 25.0, first_frame=1, append=True)
    assert path.read_bytes() == before
    assert not list(tmp_path.glob("*.partial*"))


def test_rock_alone_writes_no_particles_prim(tmp_path: pathlib.Path) -> None:
    """No spheres in any frame: no /World/Particles (an empty Points prim would carry an inverted ±FLT_MAX extent)."""
    path = tmp_path / "rock_only.usda"
    with UsdWriter(path, FPS) as writer:
        for k, frame in enumerate(story()[:2]):
            writer.write_frame(**frame)
            assert k == 0 or frame["surface"] is not None
    stage = Usd.Stage.Open(str(path))
    assert not stage.GetPrimAtPath("/World/Particles")
    assert stage.GetPrimAtPath("/World/Rock")


def subsampled_frames() -> list[dict]:
    """Four frames of spheres with ids 0..9, 0..9, 0..5 and 0..19, bonded in a chain (i, i + 1) and pairs (i, i + 4)."""
    rng = np.random.default_rng(7)
    frames = []
    for k, n in enumerate((10, 10, 6, 20)):
        chain = [(i, i + 1) for i in range(n - 1)] + [(i, i + 4) for i in range(n - 4)]
        frames.append(
            {
                "time": 0.01 * k,
                "positions": rng.normal(size=(n, 3)),
                "radii": rng.uniform(0.01, 0.05, size=n),
                "velocities": rng.normal(size=(n, 3)),
                "ids": np.arange(n, dtype=np.int64),
                "colors": rng.uniform(0.0, 1.0, size=(n, 3)),
                "bonds": np.array(chain),
                "bonds_broken": rng.integers(0, 3, size=n),
            }
        )
    return frames


def test_spheres_past_the_limit_are_subsampled_by_id(tmp_path: pathlib.Path) -> None:
    """Past ``max_spheres`` a frame holds the spheres whose id is a multiple of the stride, the smallest power of two
    with ceil(N / stride) <= max_spheres, never lowered: brute force over each frame's ids, with the bonds whose both
    ends are kept renumbered into the kept list; and a restart from frame 2 authors the same stage."""
    from stage_compare import assert_stages_equal

    frames = subsampled_frames()
    path = tmp_path / "sub.usda"
    with UsdWriter(path, FPS, max_spheres=3) as writer:
        strides = []
        for frame in frames:
            writer.write_frame(**frame)
            strides.append(writer.sphere_stride)
    # 10 spheres: 10 > 3, 5 > 3, 3 <= 3 at stride 4; 6 keeps 4 (never lowered); 20: 5 > 3 at 4, 3 at 8.
    assert strides == [4, 4, 4, 8]
    stage = Usd.Stage.Open(str(path))
    points = UsdGeom.Points(stage.GetPrimAtPath("/World/Particles"))
    stride_attr = points.GetPrim().GetAttribute("warpdem:sphereStride")
    curves = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/Bonds"))
    damage = UsdGeom.PrimvarsAPI(points.GetPrim()).GetPrimvar("bondsBroken")
    for code, (frame, stride) in enumerate(zip(frames, strides, strict=True)):
        kept = [i for i in frame["ids"] if i % stride == 0]
        np.testing.assert_array_equal(np.asarray(points.GetIdsAttr().Get(code)), kept)
        np.testing.assert_allclose(np.asarray(points.GetPointsAttr().Get(code)), frame["positions"][kept], rtol=RTOL)
        np.testing.assert_array_equal(np.asarray(damage.Get(code)), frame["bonds_broken"][kept])
        assert stride_attr.Get(code) == stride
        ends = [(a, b) for a, b in frame["bonds"] if a in kept and b in kept]
        expected = frame["positions"][np.array(ends, dtype=int).reshape(-1)]
        drawn = np.asarray(curves.GetPointsAttr().Get(code)).reshape(-1, 3)
        np.testing.assert_allclose(drawn, expected, rtol=RTOL, atol=1e-7)
    # A restart from frame 2 (the stride read back from the stage) authors what the uninterrupted writer did.
    restarted = tmp_path / "restarted.usda"
    with UsdWriter(restarted, FPS, max_spheres=3) as writer:
        for frame in frames[:3]:
            writer.write_frame(**frame)
    with UsdWriter(restarted, FPS, first_frame=2, append=True, max_spheres=3) as writer:
        assert writer.sphere_stride == 4
        for frame in frames[2:]:
            writer.write_frame(**frame)
    assert_stages_equal(Usd.Stage.Open(str(restarted)), stage)


def test_max_spheres_below_one_is_refused(tmp_path: pathlib.Path) -> None:
    with pytest.raises(ValueError, match="max_spheres must be at least 1"):
        UsdWriter(tmp_path / "x.usdc", FPS, max_spheres=0)
    assert not list(tmp_path.iterdir())

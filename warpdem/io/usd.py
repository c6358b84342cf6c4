"""Animated USD stage output for DEM particles and bonds and the FEM rock surface.

The writer authors one time sample per recorded frame. Time codes are integer frame numbers counted by the
writer (0, 1, 2, ...), so any frame rate plays back at the same speed in every USD viewer; the simulated time
of each frame is stored alongside in the time-sampled attribute ``/World.warpdem:time`` [s].

Stage layout::

    /World              Xform, default prim; custom double ``warpdem:time`` [s], one sample per frame
    /World/Particles    Points (only once a frame has spheres): points [m], widths (diameters) [m],
                        velocities [m/s], ids, primvars:displayColor (vertex), primvars:speed [m/s] (vertex),
                        extent [m], primvars:bondsBroken (vertex, int: bonds each sphere has lost so far; when given),
                        primvars:fragment (vertex, int: the fragment id of each sphere, -1 for none,
                        warpdem.stages.fragments; when given)
    /World/Bonds        BasisCurves, linear, one 2-vertex curve per bond (only when bonds are given)
    /World/Rock         Mesh of triangles (only when a frame carries a :class:`SurfaceFrame`): points [m] and
                        velocities [m/s] every frame, faceVertexCounts / faceVertexIndices only on the frames where
                        the topology changes, primvars:speed [m/s] (vertex), primvars:vonMisesStress and
                        primvars:maxPrincipalStress [Pa] (uniform: one per triangle), primvars:displayColor (uniform
                        or vertex), extent [m] of the triangles' vertices; primvars:damage [-] (vertex, float in
                        [0, 1]: the node's cohesive damage; when the surface carries it, i.e. with fracture on),
                        primvars:fragment (vertex, int: the fragment id of each node, -1 for a node without mass;
                        when the frame carries it)
    /World/Cohesive     BasisCurves, linear, one 2-vertex curve per intact cohesive element from daughter A to
                        daughter B (only when cohesive curves are given): points [m], constant width [m],
                        primvars:damage [-] and primvars:displayColor (uniform: one per curve)

The stage is authored into ``<stem>.partial<suffix>`` next to the final file and moved over the final name
with ``os.replace`` at :meth:`UsdWriter.close`, so a crashed run never leaves a half-written file under the
name a viewer or a later pipeline step would pick up. A crate stage is saved after every frame (crate saves append
the new samples and a new table of contents, the header pointing at it written last), so the partial file holds
every frame written when the process is killed (kill -9, the OOM killer, pre-emption), and a restart continues it
(``continue_partial``); :meth:`UsdWriter.flush` saves (and syncs) it on demand, before a checkpoint is written.

A restarted run continues the same animation (``append=True``): the published stage is copied to the partial
name, its time samples from the restart frame on are dropped, and the new frames are authored after the kept ones,
so one file holds the whole timeline (a sublayer cannot do that: a stronger layer's samples hide a weaker one's
completely). The original stays as it was until the extended stage is renamed over it.
"""

from __future__ import annotations

import math
import os
import pathlib
import shutil
from types import TracebackType
from typing import Any

import numpy as np

from .checkpoint import fsync_path
from .usd_frames import CurveSet, SurfaceFrame, as_float32, check_curves, check_surface, empty_curves, empty_surface

__all__ = ["CurveSet", "SurfaceFrame", "UsdWriter", "partial_stage_path", "stage_frame"]

_SUFFIXES = (".usd", ".usdc", ".usda")

# The prims a frame defines only once it carries their data; a restart drops them again where no sample is left.
_LAZY_PRIMS = ("/World/Particles", "/World/Bonds", "/World/Rock", "/World/Cohesive")

_STRIDE_ATTR = "warpdem:sphereStride"
"""The custom attribute of /World/Particles that says which spheres a frame holds: those whose id is a multiple of it
(authored from the first frame over the writer's ``max_spheres``)."""

# Radius-to-width ratio of the bond curves: thin enough to leave the spheres visible, thick enough to see.
_BOND_WIDTH_PER_MEAN_RADIUS = 0.5


class UsdWriter:
    """Writes DEM frames into an animated USD stage.

    Example::

        with UsdWriter("out/run.usdc", frames_per_second=60.0) as usd:
            for frame in frames:
                usd.write_frame(time=frame.t, positions=..., radii=..., velocities=..., ids=..., colors=...)

    Leaving the ``with`` block normally publishes the file (:meth:`close`); leaving it through an exception
    deletes the partial file (:meth:`abort`) and lets the exception propagate.

    Attributes:
        save_interval_frames: For crate files (``.usd``/``.usdc``), the partial file is saved every this many
            frames. A crate save appends the new samples and a new table of contents to the file (so saving every
            frame costs little more than saving rarely), hands the samples over to the file, which bounds the
            writer's memory, and makes them survive a killed process. Text files (``.usda``)
            are rewritten whole on every save, so they are saved only at :meth:`flush` and :meth:`close`. ``0``
            saves only there.
    """

    save_interval_frames: int = 1

    def __init__(
        self,
        path: str | os.PathLike,
        frames_per_second: float,
        *,
        comment: str | None = None,
        first_frame: int = 0,
        append: bool = False,
        continue_partial: bool = False,
        max_spheres: int | None = None,
    ) -> None:
        """Creates the partial stage and authors the stage metadata (or copies the stage a restart extends).

        Args:
            path: Final file name; the suffix picks the format: ``.usdc`` or ``.usd`` (binary crate) or
                ``.usda`` (text). Parent directories are created.
            frames_per_second: Playback rate [frames/s], stored as both ``timeCodesPerSecond`` and
                ``framesPerSecond`` since one time code is one frame.
            comment: Optional free text stored as the layer comment (e.g. the scene file and command line).
            first_frame: Time code of the first frame written (a restarted run continues the original timeline).
            append: If the final file exists, continue it: keep its samples before ``first_frame``, drop the rest,
                and author from ``first_frame`` on (its timeline start stays). Without the file, a new stage starts
                at ``first_frame``.
            continue_partial: With ``append``, continue the partial file a killed writer left (in place) rather than
                the final file; the caller has checked that it holds the frames to keep. Otherwise a partial file on
                disk is deleted.
            max_spheres: Past this many spheres in a frame, only the spheres whose id is a multiple of a stride (a
                power of two, the smallest that brings the frame within the limit, never lowered again, so that the
                same spheres stay drawn) are written, with their bonds between them; the stride is authored as
                ``/World/Particles.warpdem:sphereStride`` and kept as :attr:`sphere_stride`. None: every sphere.

        Raises:
            ValueError: If the suffix is not one of ``.usd``, ``.usdc``, ``.usda``, the frame rate is not a
                positive finite number, or the stage to append to has another frame rate or cannot be opened.
            RuntimeError: If another writer in this process is already authoring the same file.
        """
        from pxr import Sdf, Usd, UsdGeom

        final_path = pathlib.Path(path)
        suffix = final_path.suffix.lower()
        if suffix not in _SUFFIXES:
            raise ValueError(
                f"USD output {str(final_path)!r}: unsupported suffix {final_path.suffix!r}, "
                f"expected one of {', '.join(_SUFFIXES)}"
            )
        fps = float(frames_per_second)
        if not (math.isfinite(fps) and fps > 0.0):
            raise ValueError(f"USD output {str(final_path)!r}: frames_per_second must be > 0, got {frames_per_second}")
        if max_spheres is not None and max_spheres < 1:
            raise ValueError(f"USD output {str(final_path)!r}: max_spheres must be at least 1, got {max_spheres}")

        final_path.parent.mkdir(parents=True, exist_ok=True)
        final_path = final_path.resolve()
        partial_path = partial_stage_path(final_path)
        if Sdf.Layer.Find(str(partial_path)) is not None:
            raise RuntimeError(f"USD output {str(final_path)!r} is already being written by another writer")
        resume_partial = append and continue_partial and partial_path.exists()
        if not resume_partial:
            # A partial file the caller does not continue is the leftover of another run.
            partial_path.unlink(missing_ok=True)

        existing = append and (resume_partial or final_path.exists())
        if existing:
            if not resume_partial:
                shutil.copyfile(final_path, partial_path)
            layer = Sdf.Layer.FindOrOpen(str(partial_path))
            if layer is None:
                if not resume_partial:  # a killed run's frames are never deleted
                    partial_path.unlink(missing_ok=True)
                raise ValueError(f"USD output {str(final_path)!r}: cannot open the stage to extend")
        else:
            # ".usd" may be either encoding; the brief for this format is crate, whatever USD_DEFAULT_FILE_FORMAT says.
            layer_args = {"format": "usdc"} if suffix == ".usd" else {}
            layer = Sdf.Layer.CreateNew(str(partial_path), args=layer_args)
            if layer is None:
                raise RuntimeError(f"USD output {str(final_path)!r}: could not create {str(partial_path)!r}")
        if comment is not None:
            layer.comment = comment
        stage = Usd.Stage.Open(layer)

        if existing:
            rate = stage.GetTimeCodesPerSecond()
            if rate != fps:
                layer = stage = None
                if not resume_partial:  # a killed run's frames are never deleted
                    partial_path.unlink(missing_ok=True)
                raise ValueError(
                    f"USD output {str(final_path)!r}: its frame rate is {rate:g} frames/s, this run's {fps:g}; "
                    "cannot continue its timeline"
                )
            start = min(stage.GetStartTimeCode(), float(first_frame))
            _drop_samples_from(stage, float(first_frame))
        else:
            UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
            UsdGeom.SetStageMetersPerUnit(stage, 1.0)
            stage.SetTimeCodesPerSecond(fps)
            stage.SetFramesPerSecond(fps)
            start = float(first_frame)
        stage.SetStartTimeCode(start)
        stage.SetEndTimeCode(start)

        world = UsdGeom.Xform.Define(stage, "/World")
        stage.SetDefaultPrim(world.GetPrim())
        self._time_attr = world.GetPrim().CreateAttribute("warpdem:time", Sdf.ValueTypeNames.Double, custom=True)

        self._final_path = final_path
        self._partial_path = partial_path
        self._crate = suffix in (".usd", ".usdc")
        self._layer: Any = layer
        self._stage: Any = stage
        self._points: Any = None  # UsdGeom.Points, defined on the first frame that carries spheres
        self._particle_attrs: dict[str, Any] = {}
        self._bonds: Any = None  # UsdGeom.BasisCurves, defined on the first frame that carries bonds
        self._rock: Any = None  # UsdGeom.Mesh, defined on the first frame that carries a surface
        self._rock_attrs: dict[str, Any] = {}
        self._rock_vertex_colors = False
        self._cohesive: Any = None  # UsdGeom.BasisCurves, defined on the first frame that carries cohesive curves
        self._cohesive_attrs: dict[str, Any] = {}
        self._last_faces: np.ndarray | None = None
        self._last_ids: np.ndarray | None = None
        self._damage_primvar: Any = None  # primvars:bondsBroken, defined on the first frame that carries it
        self._fragment_primvars: dict[str, Any] = {}  # primvars:fragment of the spheres and the rock, likewise
        self._frame_count = 0
        self._open_code: float | None = None  # the time code of a frame being authored (None between frames)
        self._first_frame = int(first_frame)
        self._start = start  # time code of the stage's first frame (before first_frame in an extended stage)
        self._closed = False
        self.extended = existing
        """Whether this writer continues an existing stage (``append`` and the file was there)."""
        self._continues_partial = resume_partial  # the partial file holds a killed run's frames: never deleted
        self.max_spheres = max_spheres
        self.sphere_stride = 1
        """The ids a frame's spheres are written at: the multiples of this (1: all)."""
        self._stride_authored = 1  # the stride the stage holds (1 where none is authored)
        if existing:
            self._attach(float(first_frame) - 1.0)

    def _attach(self, code: float) -> None:
        """Takes over the prims of an extended stage, and the ids and triangles it holds at ``code`` (the frame
        before the first one this writer authors), so that the next frames author exactly what an uninterrupted
        writer would have."""
        from pxr import UsdGeom

        if self._stage.GetPrimAtPath("/World/Particles"):
            self._define_particles()
            ids = self._particle_attrs["ids"]
            if ids.GetNumTimeSamples():
                self._last_ids = np.asarray(ids.Get(code), dtype=np.int64)
            stride = self._points.GetPrim().GetAttribute(_STRIDE_ATTR)
            if stride and stride.GetNumTimeSamples():
                self.sphere_stride = self._stride_authored = int(stride.Get(code))
        if self._stage.GetPrimAtPath("/World/Bonds"):
            self._define_bonds()
        rock = self._stage.GetPrimAtPath("/World/Rock")
        if rock:
            color = UsdGeom.Mesh(rock).GetDisplayColorPrimvar()
            damage = UsdGeom.PrimvarsAPI(rock).HasPrimvar("damage")
            self._define_rock(color.GetInterpolation() == UsdGeom.Tokens.vertex, damage)
            indices = self._rock_attrs["indices"]
            if indices.GetNumTimeSamples():
                self._last_faces = np.asarray(indices.Get(code), dtype=np.int32).reshape(-1, 3)
        if self._stage.GetPrimAtPath("/World/Cohesive"):
            self._define_cohesive()

    def _define_particles(self) -> None:
        """Defines /World/Particles and its attributes (or takes over those of an extended stage)."""
        from pxr import Sdf, UsdGeom

        points = UsdGeom.Points.Define(self._stage, "/World/Particles")
        points.SetWidthsInterpolation(UsdGeom.Tokens.vertex)
        self._points = points
        self._particle_attrs = {
            "points": points.CreatePointsAttr(),
            "widths": points.CreateWidthsAttr(),
            "velocities": points.CreateVelocitiesAttr(),
            "ids": points.CreateIdsAttr(),
            "extent": points.CreateExtentAttr(),
            "color": points.CreateDisplayColorPrimvar(UsdGeom.Tokens.vertex),
            "speed": UsdGeom.PrimvarsAPI(points.GetPrim()).CreatePrimvar(
                "speed", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex
            ),
        }

    @property
    def frame_count(self) -> int:
        """Number of frames written so far (the next frame's time code is ``first_frame`` + this)."""
        return self._frame_count

    @property
    def path(self) -> pathlib.Path:
        """Final (published) file path."""
        return self._final_path

    @property
    def partial_path(self) -> pathlib.Path:
        """Temporary file the stage is authored into until :meth:`close`."""
        return self._partial_path

    def write_frame(
        self,
        *,
        time: float,
        positions: np.ndarray,
        radii: np.ndarray,
        velocities: np.ndarray,
        ids: np.ndarray,
        colors: np.ndarray,
        bonds: np.ndarray | None = None,
        surface: SurfaceFrame | None = None,
        bonds_broken: np.ndarray | None = None,
        cohesive: CurveSet | None = None,
        fragments: np.ndarray | None = None,
    ) -> int:
        """Authors one frame of particle (and optionally bond and rock surface) data.

        Args:
            time: Simulated time of the frame [s], stored in ``/World.warpdem:time``.
            positions: Particle centres [m], shape (N, 3).
            radii: Particle radii [m], shape (N,); written as widths = diameters.
            velocities: Particle velocities [m/s], shape (N, 3).
            ids: Stable particle ids, shape (N,), integer. Authored only at frame 0 and whenever N or the id list
                changes; USD holds the last sample in between.
            colors: Display colours, linear RGB in [0, 1], shape (N, 3).
            bonds: Optional bonded pairs as indices into this frame's arrays, shape (M, 2), integer. Once any
                frame has carried bonds, a later frame without them authors an empty bond set so stale bonds
                are not drawn.
            surface: Optional rock surface, written to ``/World/Rock``. Its topology is authored only where it
                differs from the last authored one (USD holds it in between); once any frame has carried a surface,
                a later frame without one authors an empty mesh.
            bonds_broken: Optional bonds each sphere has lost so far, shape (N,), integer (a damage measure),
                written to ``primvars:bondsBroken``.
            cohesive: Optional cohesive elements as curves, written to ``/World/Cohesive``; once any frame has
                carried them, a later frame without them authors an empty set.
            fragments: Optional fragment id of each sphere, shape (N,), integer (-1 for none), written to
                ``primvars:fragment``.

        Returns:
            The time code (frame number) of the frame just written.

        Raises:
            ValueError: If array shapes disagree, ids or bonds are not integers, or a bond index is out of range.
            RuntimeError: If the writer is already closed or aborted.
        """
        from pxr import Vt

        self._check_open()
        t = float(time)
        if not math.isfinite(t):
            raise ValueError(f"USD frame {self._frame_count}: time must be finite, got {time}")
        pos = as_float32(positions, "positions", (-1, 3))
        n = pos.shape[0]
        rad = as_float32(radii, "radii", (n,))
        vel = as_float32(velocities, "velocities", (n, 3))
        col = as_float32(colors, "colors", (n, 3))
        ids_arr = np.asarray(ids)
        if ids_arr.shape != (n,) or not np.issubdtype(ids_arr.dtype, np.integer):
            raise ValueError(f"ids: expected integer array of shape ({n},), got {ids_arr.dtype} {ids_arr.shape}")
        ids_arr = np.ascontiguousarray(ids_arr, dtype=np.int64)
        bond_arr = None
        if bonds is not None:
            bond_arr = np.asarray(bonds)
            if bond_arr.ndim != 2 or bond_arr.shape[1] != 2 or not np.issubdtype(bond_arr.dtype, np.integer):
                raise ValueError(
                    f"bonds: expected integer array of shape (M, 2), got {bond_arr.dtype} {bond_arr.shape}"
                )
            if bond_arr.size and (bond_arr.min() < 0 or bond_arr.max() >= n):
                raise ValueError(f"bonds: indices must lie in [0, {n}), got range [{bond_arr.min()}, {bond_arr.max()}]")
        checked_surface = check_surface(surface) if surface is not None else None
        checked_cohesive = check_curves(cohesive) if cohesive is not None else None
        if self.max_spheres is not None:
            while -(-n // self.sphere_stride) > self.max_spheres:
                self.sphere_stride *= 2
        if self.sphere_stride > 1 and n:
            keep = ids_arr % self.sphere_stride == 0
            pos, rad, vel, col, ids_arr = pos[keep], rad[keep], vel[keep], col[keep], ids_arr[keep]
            if bonds_broken is not None:
                bonds_broken = np.asarray(bonds_broken).reshape(n)[keep]
            if fragments is not None:
                fragments = np.asarray(fragments).reshape(n)[keep]
            if bond_arr is not None:
                renumber = np.cumsum(keep) - 1  # a kept sphere's index among the kept
                bond_arr = renumber[bond_arr[keep[bond_arr[:, 0]] & keep[bond_arr[:, 1]]]]
            n = len(ids_arr)

        code = float(self._first_frame + self._frame_count)
        # Until the frame is complete, :meth:`close` drops what it authored (an interrupt inside this method).
        self._open_code = code
        self._time_attr.Set(t, code)
        # A scene of rock alone has no /World/Particles (an empty Points prim would carry an inverted extent).
        if n and self._points is None:
            self._define_particles()
            if code > self._start:
                # USD holds the first sample backwards in time: frames before the spheres existed draw none.
                none3 = np.zeros((0, 3), np.float32)
                self._set_particles(code - 1.0, none3, none3, np.zeros(0, np.float32), none3)
        if self._points is not None:
            self._set_particles(code, pos, vel, rad, col)
            if self.sphere_stride != self._stride_authored:
                from pxr import Sdf

                attr = self._points.GetPrim().CreateAttribute(_STRIDE_ATTR, Sdf.ValueTypeNames.Int, custom=True)
                attr.Set(self.sphere_stride, code)
                self._stride_authored = self.sphere_stride
            # ids are only needed where the particle set changes; held samples keep the file small.
            if self._last_ids is None or not np.array_equal(self._last_ids, ids_arr):
                self._particle_attrs["ids"].Set(Vt.Int64Array.FromNumpy(ids_arr), code)
                self._last_ids = ids_arr.copy()

        if bonds_broken is not None and self._points is not None:
            damage = np.ascontiguousarray(np.asarray(bonds_broken).reshape(n), dtype=np.int32)
            if self._damage_primvar is None:
                from pxr import Sdf, UsdGeom

                self._damage_primvar = UsdGeom.PrimvarsAPI(self._points.GetPrim()).CreatePrimvar(
                    "bondsBroken", Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.vertex
                )
            self._damage_primvar.Set(Vt.IntArray.FromNumpy(damage), code)

        if fragments is not None and self._points is not None:
            self._set_fragment("/World/Particles", self._points.GetPrim(), code, np.asarray(fragments).reshape(n))

        if bond_arr is not None:
            self._write_bonds(code, pos, rad, bond_arr)
        elif self._bonds is not None:
            self._write_bonds(code, pos, rad, np.zeros((0, 2), dtype=np.int64))

        if checked_surface is not None:
            self._write_surface(code, *checked_surface)
            if surface.fragment is not None:
                label = np.asarray(surface.fragment).reshape(len(checked_surface[0]))
                self._set_fragment("/World/Rock", self._rock.GetPrim(), code, label)
        elif self._rock is not None:
            self._write_surface(code, *empty_surface(), self._rock_vertex_colors, None)

        if checked_cohesive is not None:
            self._write_cohesive(code, *checked_cohesive)
        elif self._cohesive is not None:
            self._write_cohesive(code, *empty_curves())

        self._frame_count += 1
        self._open_code = None
        if self._crate and self.save_interval_frames > 0 and self._frame_count % self.save_interval_frames == 0:
            self._save()
        return int(code)

    def flush(self, sync: bool = False) -> None:
        """Saves the partial file now, so that it holds every frame written (also a text stage).

        Args:
            sync: Also force the file to the disk (``os.fsync``), so that it survives a power loss; done before a
                checkpoint is written, so that the stage holds the checkpoint's frame whatever happens after.

        Raises:
            RuntimeError: If the writer is closed, or the save fails.
        """
        self._check_open()
        self._save()
        if sync:
            fsync_path(self._partial_path)

    def _save(self) -> None:
        """Saves the layer with the timeline ending at the last complete frame."""
        self._stage.SetStartTimeCode(self._start)
        self._stage.SetEndTimeCode(max(self._start, float(self._first_frame + self._frame_count - 1)))
        if not self._layer.Save():
            raise RuntimeError(f"USD output {str(self._final_path)!r}: saving {str(self._partial_path)!r} failed")

    def _set_fragment(self, path: str, prim: Any, code: float, label: np.ndarray) -> None:
        """Sets ``primvars:fragment`` (vertex, int) of a prim at one time code, defining it on first use."""
        from pxr import Sdf, UsdGeom, Vt

        primvar = self._fragment_primvars.get(path)
        if primvar is None:
            primvar = UsdGeom.PrimvarsAPI(prim).CreatePrimvar(
                "fragment", Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.vertex
            )
            self._fragment_primvars[path] = primvar
        primvar.Set(Vt.IntArray.FromNumpy(np.ascontiguousarray(label, dtype=np.int32)), code)

    def _set_particles(self, code: float, pos: np.ndarray, vel: np.ndarray, rad: np.ndarray, col: np.ndarray) -> None:
        """Sets the sphere attributes but ids at one time code (float32 arrays, as :meth:`write_frame` checked)."""
        from pxr import Vt

        a = self._particle_attrs
        widths = Vt.FloatArray.FromNumpy(2.0 * rad)
        points = Vt.Vec3fArray.FromNumpy(pos)
        a["points"].Set(points, code)
        a["widths"].Set(widths, code)
        a["velocities"].Set(Vt.Vec3fArray.FromNumpy(vel), code)
        a["color"].Set(Vt.Vec3fArray.FromNumpy(col), code)
        a["speed"].Set(Vt.FloatArray.FromNumpy(np.linalg.norm(vel, axis=1).astype(np.float32)), code)
        a["extent"].Set(self._points.ComputeExtent(points, widths), code)

    def close(self) -> pathlib.Path:
        """Saves the stage and atomically moves it to the final path.

        Returns:
            The final file path.

        Raises:
            RuntimeError: If the writer is already closed or aborted.
        """
        self._check_open()
        try:
            if self._open_code is not None:
                # Interrupted while authoring a frame: publish the complete frames only.
                _drop_samples_from(self._stage, self._open_code)
                self._open_code = None
            self._save()
        except BaseException:
            self.abort()
            raise
        # Release the layer before the rename so no memory map still points at the old name.
        self._release()
        try:
            fsync_path(self._partial_path)
            os.replace(self._partial_path, self._final_path)
            fsync_path(self._final_path.parent)
        except BaseException:
            self._partial_path.unlink(missing_ok=True)
            raise
        return self._final_path

    def abort(self) -> None:
        """Drops the stage and deletes the partial file; the final path is left as it was. A partial file this
        writer continues (``continue_partial``) is kept: it holds the frames of the run that left it, as saved.

        Does nothing if the writer is already closed or aborted.
        """
        if self._closed:
            return
        self._release()
        if not self._continues_partial:
            self._partial_path.unlink(missing_ok=True)

    def __enter__(self) -> UsdWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        if exc_type is None:
            if not self._closed:
                self.close()
        else:
            self.abort()

    def _write_bonds(self, code: float, pos: np.ndarray, rad: np.ndarray, bonds: np.ndarray) -> None:
        """Authors the bond curves of one frame.

        Args:
            code: Time code of the frame.
            pos: Particle centres [m], shape (N, 3), float32.
            rad: Particle radii [m], shape (N,), float32.
            bonds: Bonded pairs, shape (M, 2), integer indices into ``pos``.
        """
        if self._bonds is None:
            self._define_bonds()
            if code > 0.0:
                # USD holds the first sample backwards in time; an empty sample before it keeps earlier frames
                # from drawing bonds that did not exist yet.
                _set_curves(self._bonds, code - 1.0, np.zeros((0, 3), np.float32), 0.0)

        endpoints = np.ascontiguousarray(pos[bonds.reshape(-1)], dtype=np.float32)
        width = _BOND_WIDTH_PER_MEAN_RADIUS * float(rad.mean()) if rad.size else 0.0
        _set_curves(self._bonds, code, endpoints, width)

    def _define_bonds(self) -> None:
        """Defines /World/Bonds (or takes over that of an extended stage)."""
        self._bonds = _define_curves(self._stage, "/World/Bonds")

    def _write_cohesive(
        self, code: float, endpoints: np.ndarray, width: float, damage: np.ndarray, colors: np.ndarray
    ) -> None:
        """Authors the cohesive element curves of one frame (arguments as :class:`CurveSet`, checked: endpoints
        flattened to shape (2 M, 3), float32 arrays)."""
        from pxr import Vt

        if self._cohesive is None:
            self._define_cohesive()
            if code > self._start:
                # USD holds the first sample backwards in time: frames before the elements existed draw none.
                self._write_cohesive(code - 1.0, *empty_curves())
        _set_curves(self._cohesive, code, endpoints, width)
        self._cohesive_attrs["damage"].Set(Vt.FloatArray.FromNumpy(damage), code)
        self._cohesive_attrs["color"].Set(Vt.Vec3fArray.FromNumpy(colors), code)

    def _define_cohesive(self) -> None:
        """Defines /World/Cohesive and its primvars (or takes over those of an extended stage)."""
        from pxr import Sdf, UsdGeom

        curves = _define_curves(self._stage, "/World/Cohesive")
        self._cohesive = curves
        self._cohesive_attrs = {
            "damage": UsdGeom.PrimvarsAPI(curves.GetPrim()).CreatePrimvar(
                "damage", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.uniform
            ),
            "color": curves.CreateDisplayColorPrimvar(UsdGeom.Tokens.uniform),
        }

    def _write_surface(
        self,
        code: float,
        points: np.ndarray,
        faces: np.ndarray,
        velocities: np.ndarray,
        von_mises: np.ndarray,
        max_principal: np.ndarray,
        colors: np.ndarray,
        vertex_colors: bool,
        damage: np.ndarray | None,
    ) -> None:
        """Authors the rock surface of one frame (arguments as :class:`SurfaceFrame`, checked and converted). Once
        the damage primvar exists, a frame without damage authors an empty one (as the triangles of a vanished rock),
        so no frame holds another frame's values."""
        from pxr import Gf, Vt

        if self._rock is None:
            self._define_rock(vertex_colors, damage is not None)
            if code > self._start:
                # USD holds the first sample backwards in time: frames before the surface existed draw nothing.
                self._write_surface(code - 1.0, *empty_surface(), vertex_colors, None)
        elif damage is not None and "damage" not in self._rock_attrs:
            self._define_rock_damage()
        a = self._rock_attrs
        if self._last_faces is None or not np.array_equal(self._last_faces, faces):
            a["counts"].Set(Vt.IntArray.FromNumpy(np.full(len(faces), 3, dtype=np.int32)), code)
            a["indices"].Set(Vt.IntArray.FromNumpy(np.ascontiguousarray(faces.reshape(-1))), code)
            self._last_faces = faces.copy()
        a["points"].Set(Vt.Vec3fArray.FromNumpy(points), code)
        a["velocities"].Set(Vt.Vec3fArray.FromNumpy(velocities), code)
        a["speed"].Set(Vt.FloatArray.FromNumpy(np.linalg.norm(velocities, axis=1).astype(np.float32)), code)
        a["von_mises"].Set(Vt.FloatArray.FromNumpy(von_mises), code)
        a["max_principal"].Set(Vt.FloatArray.FromNumpy(max_principal), code)
        a["color"].Set(Vt.Vec3fArray.FromNumpy(colors), code)
        if "damage" in a:
            a["damage"].Set(Vt.FloatArray.FromNumpy(damage if damage is not None else np.zeros(0, np.float32)), code)
        if faces.size:
            used = points[faces.reshape(-1)]
            lo, hi = used.min(axis=0), used.max(axis=0)
        else:
            lo = np.full(3, np.finfo(np.float32).max)
            hi = -lo
        a["extent"].Set(Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]), code)

    def _define_rock(self, vertex_colors: bool, damage: bool) -> None:
        """Defines /World/Rock and its attributes, with the damage primvar when ``damage`` (or takes over those of
        an extended stage)."""
        from pxr import Sdf, UsdGeom

        mesh = UsdGeom.Mesh.Define(self._stage, "/World/Rock")
        # Flat triangles of a FEM surface: a subdivision surface would round off the cracks.
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        primvars = UsdGeom.PrimvarsAPI(mesh.GetPrim())
        self._rock = mesh
        self._rock_vertex_colors = vertex_colors
        self._rock_attrs = {
            "points": mesh.CreatePointsAttr(),
            "velocities": mesh.CreateVelocitiesAttr(),
            "counts": mesh.CreateFaceVertexCountsAttr(),
            "indices": mesh.CreateFaceVertexIndicesAttr(),
            "extent": mesh.CreateExtentAttr(),
            "color": mesh.CreateDisplayColorPrimvar(UsdGeom.Tokens.vertex if vertex_colors else UsdGeom.Tokens.uniform),
            "speed": primvars.CreatePrimvar("speed", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex),
            "von_mises": primvars.CreatePrimvar(
                "vonMisesStress", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.uniform
            ),
            "max_principal": primvars.CreatePrimvar(
                "maxPrincipalStress", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.uniform
            ),
        }
        if damage:
            self._define_rock_damage()

    def _define_rock_damage(self) -> None:
        """Defines the damage primvar of /World/Rock (or takes over that of an extended stage)."""
        from pxr import Sdf, UsdGeom

        self._rock_attrs["damage"] = UsdGeom.PrimvarsAPI(self._rock.GetPrim()).CreatePrimvar(
            "damage", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex
        )

    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError(f"USD output {str(self._final_path)!r}: writer is already closed")

    def _release(self) -> None:
        """Drops every handle on the stage so USD releases the layer."""
        self._closed = True
        self._time_attr = self._damage_primvar = None
        self._fragment_primvars = {}
        self._points = self._bonds = self._rock = self._cohesive = None
        self._particle_attrs = {}
        self._rock_attrs = {}
        self._cohesive_attrs = {}
        self._stage = None
        self._layer = None


def partial_stage_path(path: str | os.PathLike) -> pathlib.Path:
    """The temporary name a stage is authored under until it is published: ``<stem>.partial<suffix>`` beside it
    (USD picks the file format from the extension, so the suffix stays last)."""
    final = pathlib.Path(path)
    return final.with_name(f"{final.stem}.partial{final.suffix}")


def _define_curves(stage: Any, path: str) -> Any:
    """Defines linear BasisCurves with one constant width at ``path`` (or takes over those of an extended stage)."""
    from pxr import UsdGeom

    curves = UsdGeom.BasisCurves.Define(stage, path)
    curves.CreateTypeAttr(UsdGeom.Tokens.linear)
    curves.CreateWidthsAttr()
    curves.SetWidthsInterpolation(UsdGeom.Tokens.constant)
    return curves


def _set_curves(curves: Any, code: float, endpoints: np.ndarray, width: float) -> None:
    """Sets the points, vertex counts, width and extent of two-point curves at one time code.

    Args:
        curves: UsdGeom.BasisCurves (from :func:`_define_curves`).
        code: Time code.
        endpoints: Curve vertices [m], the two ends of each curve in turn, shape (2 M, 3), float32.
        width: Constant curve width [m].
    """
    from pxr import Gf, Vt

    curves.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(endpoints), code)
    counts = np.full(endpoints.shape[0] // 2, 2, dtype=np.int32)
    curves.GetCurveVertexCountsAttr().Set(Vt.IntArray.FromNumpy(counts), code)
    curves.GetWidthsAttr().Set(Vt.FloatArray([width]), code)
    if endpoints.shape[0]:
        half = 0.5 * width
        lo = endpoints.min(axis=0) - half
        hi = endpoints.max(axis=0) + half
    else:
        # USD's empty range: min above max.
        lo = np.full(3, np.finfo(np.float32).max)
        hi = -lo
    curves.GetExtentAttr().Set(Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]), code)


def _drop_samples_from(stage: Any, code: float) -> None:
    """Clears every time sample at or after ``code`` on every attribute of a stage, and removes the prims a frame
    defines (:data:`_LAZY_PRIMS`) that are left without any sample: the stage then reads as if it had been written
    up to ``code`` - 1 only."""
    for prim in stage.Traverse():
        for attr in prim.GetAttributes():
            for t in attr.GetTimeSamples():
                if t >= code:
                    attr.ClearAtTime(t)
    for path in _LAZY_PRIMS:
        prim = stage.GetPrimAtPath(path)
        if prim and not any(attr.GetNumTimeSamples() for attr in prim.GetAttributes()):
            stage.RemovePrim(path)


def stage_frame(path: str | os.PathLike, code: int) -> tuple[float, float | None, np.ndarray | None, int]:
    """What a stage written by :class:`UsdWriter` holds at one frame: its frame rate [frames/s], the simulated time
    [s] of the frame (``/World.warpdem:time``; None where there is no such sample), the sphere centres [m]
    (float32, shape (N, 3); None without spheres at that frame) and the stride of the ids they are (1: every sphere;
    :attr:`UsdWriter.sphere_stride`).

    Raises:
        ValueError: If the file cannot be opened as a USD stage.
    """
    from pxr import Tf, Usd

    try:
        stage = Usd.Stage.Open(str(path))
    except Tf.ErrorException as exc:
        raise ValueError(f"{path}: not a USD stage ({' '.join(str(exc).split())})") from None
    if stage is None:
        raise ValueError(f"{path}: not a USD stage")
    world = stage.GetPrimAtPath("/World")
    time_attr = world.GetAttribute("warpdem:time") if world else None
    time = float(time_attr.Get(code)) if time_attr and code in time_attr.GetTimeSamples() else None
    particles = stage.GetPrimAtPath("/World/Particles")
    points_attr = particles.GetAttribute("points") if particles else None
    points = None
    if points_attr and points_attr.GetNumTimeSamples():
        points = np.asarray(points_attr.Get(code), dtype=np.float32).reshape(-1, 3)
    stride_attr = particles.GetAttribute(_STRIDE_ATTR) if particles else None
    stride = int(stride_attr.Get(code)) if stride_attr and stride_attr.GetNumTimeSamples() else 1
    return stage.GetTimeCodesPerSecond(), time, points, stride

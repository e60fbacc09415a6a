"""USD export: one ``UsdGeom.Mesh`` per cloth piece with time-sampled points and normals, obstacles as meshes
under time-sampled transforms. Needs ``usd-core`` (the ``usd`` extra).

Layout of the stage (``upAxis = "Z"``, ``metersPerUnit = 1``, ``timeCodesPerSecond = framesPerSecond`` = the
run's frame rate, a frame's time code = its time x that rate)::

    /World                         Xform (the default prim)
    /World/cloth/piece_0 ...       Mesh: faceVertexIndices (piece-local), points and normals at every time code,
                                   extent, primvars:st (grid cloths),
                                   primvars:sourceVertexIndex (int, vertex): the run's vertex index of each point
    /World/obstacles/obstacle_K_SHAPE   Mesh in the shape's local frame under a matrix xformOp (time-sampled
                                   when the obstacle moves, placed by the collision code's own motion)

Points are stored as 32-bit floats (USD's ``point3f[]``).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..results import Run, vertex_normals
from .staging import staged_path


def _matrix(c: np.ndarray, R: np.ndarray):
    """USD's row-vector matrix of ``x = c + R p``: upper 3x3 = R^T, last row = c."""
    from pxr import Gf

    m = np.eye(4)
    m[:3, :3] = R.T
    m[3, :3] = c
    return Gf.Matrix4d(m.tolist())


def _extent(p: np.ndarray):
    from pxr import Vt

    return Vt.Vec3fArray.FromNumpy(np.stack([p.min(0), p.max(0)]).astype(np.float32))


def write_usd(run: Run, frames: list[int], path: str | os.PathLike[str]) -> Path:
    """Write the chosen frames of ``run`` to a USD file at ``path`` (``.usd``/``.usdc`` binary, ``.usda`` text)."""
    from pxr import Sdf, Usd, UsdGeom, Vt

    path = Path(path)
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetTimeCodesPerSecond(run.fps)
    stage.SetFramesPerSecond(run.fps)
    codes = [float(c) for c in run.time_codes()[frames]]
    stage.SetStartTimeCode(codes[0])
    stage.SetEndTimeCode(codes[-1])
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())
    UsdGeom.Scope.Define(stage, "/World/cloth")
    positions = run.positions[frames]
    normals = vertex_normals(positions, run.faces)
    uvs = run.uvs()
    for k, verts in enumerate(run.pieces()):
        local = np.full(run.positions.shape[1], -1, np.int64)
        local[verts] = np.arange(len(verts))
        faces = local[run.faces[np.isin(run.faces[:, 0], verts)]]
        mesh = UsdGeom.Mesh.Define(stage, f"/World/cloth/piece_{k}")
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, np.int32)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(faces.ravel().astype(np.int32)))
        api = UsdGeom.PrimvarsAPI(mesh)
        api.CreatePrimvar("sourceVertexIndex", Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.vertex).Set(
            Vt.IntArray.FromNumpy(verts.astype(np.int32)))
        if uvs is not None:
            api.CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex).Set(
                Vt.Vec2fArray.FromNumpy(uvs[verts].astype(np.float32)))
        points, nrm, ext = mesh.CreatePointsAttr(), mesh.CreateNormalsAttr(), mesh.CreateExtentAttr()
        mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
        for f, code in enumerate(codes):
            p = positions[f][verts]
            points.Set(Vt.Vec3fArray.FromNumpy(p.astype(np.float32)), code)
            nrm.Set(Vt.Vec3fArray.FromNumpy(normals[f][verts].astype(np.float32)), code)
            ext.Set(_extent(p), code)
    obstacles = run.obstacles()
    if obstacles:
        UsdGeom.Scope.Define(stage, "/World/obstacles")
    for ob in obstacles:
        mesh = UsdGeom.Mesh.Define(stage, f"/World/obstacles/{ob.name}")
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(ob.faces), 3, np.int32)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(ob.faces.ravel().astype(np.int32)))
        mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(ob.vertices.astype(np.float32)))
        mesh.CreateExtentAttr(_extent(ob.vertices))
        op = mesh.AddTransformOp()
        if ob.motion.moving:
            for f, code in zip(frames, codes):
                op.Set(_matrix(*ob.pose(run.times[f])), code)
        else:
            op.Set(_matrix(*ob.pose(run.times[frames[0]])))
    with staged_path(path) as tmp:
        if not stage.GetRootLayer().Export(str(tmp)):
            raise OSError(f"USD could not write {path}")
    return path

"""Compiled twins of the bake's hot numpy loops: warp kernels on the CPU, for large conversions.

A 10,000-frame, 101-joint rig is a million bone matrices. numpy evaluates each step of the bake
as a series of whole-array passes over them (each a temporary of tens of megabytes), which is where
a large conversion spent its time (benchmarks/README.md, "Faster single conversions"). The kernels
here make one pass per matrix, in float64 like their numpy twins, with floating-point contraction
off (no fused multiply-add), so they do the same IEEE operations in the same order on every machine.

=================================  ==========================================================
function                           numpy twin
=================================  ==========================================================
:func:`near_rotation_polar`        ``format.encoding._near_rotation_polar``
:func:`encode_cross_matrix`        ``format.encoding.encode_bones`` (crossMatrix)
:func:`skinning_transforms`        ``converters.usdskel.AllFramesSkinning`` (local transforms,
                                   hierarchy, inverse bind, the skeleton's world transform)
:func:`bone_box_bounds`            ``decoders.bounds._bone_box_bounds`` (the bones' boxes at
                                   every sample time)
:func:`skin_lbs`                   ``decoders.reference.skin`` (linear blend skinning)
=================================  ==========================================================

Each wrapper returns None when its kernel should not run: the work is small (under
:data:`MIN_ITEMS`, where importing warp would cost more than it saves) or warp's CPU backend is not
available; the caller then runs the numpy twin, which gives the same result to rounding
(tests/test_bake_kernels.py compares every pair). Work is split over the usable cores
(``$VBUSD_THREADS``, :mod:`vbusd.process.parallel`): warp releases Python's lock while a CPU kernel runs, so
one launch per thread runs in parallel.

Warp compiles this module once per machine and warp version into its kernel cache (a few
seconds; ``python -m vbusd.kernels.bake`` does it ahead of time); later processes load it in
milliseconds.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Optional

import numpy as np

from vbusd.process.parallel import split_work
import sys

__all__ = ["MIN_ITEMS", "ENCODING_IDS", "available", "split_work", "near_rotation_polar", "encode_cross_matrix",
           "skinning_transforms", "bone_box_bounds", "skin_lbs"]

MIN_ITEMS = 65_536
"""Smallest work (matrices, bone samples or skinned points) for which the kernels are used."""

ENCODING_IDS = {"crossMatrix": 0, "affineMatrix": 1, "quatTranslation": 2}
"""Encodings :func:`bone_box_bounds` decodes (linear blend; dualQuat bounds come from points)."""

_state: dict = {}
_lock = threading.Lock()  # loading the kernels


def _kernels():
    """The compiled kernels (a namespace), or None where warp's CPU backend cannot run them.

    A helper thread never loads them (no import off the main thread: vbusd/process/threads.py): there,
    kernels that the job did not load beforehand are None, and the numpy twin runs.
    """
    if "kernels" in _state:
        return _state["kernels"]
    if threading.current_thread().name.startswith("vbusd-"):
        return None
    with _lock:
        if "kernels" not in _state:
            _state["kernels"] = None
            try:
                from vbusd.kernels.warp_setup import _init_warp, quiet_warp

                _init_warp()
                import warp as wp

                if wp.is_cpu_available():
                    from vbusd.kernels import bake_wp as compiled  # imports warp: only where the kernels run

                    with quiet_warp():
                        wp.load_module(compiled, device="cpu")
                    _state["kernels"] = compiled
            except Exception as error:  # noqa: BLE001 - no compiler, no writable kernel cache: numpy twins
                _state["kernels"] = None
                _state["why"] = " ".join(f"{type(error).__name__}: {error}".split())[:300]
        return _state["kernels"]


def available() -> bool:
    """Whether the kernels can run here (warp's CPU backend loads and the module compiles)."""
    return _kernels() is not None


def _wanted(items: int):
    return _kernels() if items >= MIN_ITEMS else None


def _array(values: np.ndarray, dtype):
    import warp as wp

    return wp.array(np.ascontiguousarray(values), dtype=dtype, device="cpu", copy=False)


def near_rotation_polar(linear: np.ndarray, tolerance: float) -> Optional[tuple]:
    """The rotations nearest to matrices that all lie within ``tolerance`` of one (kernel twin of
    ``encoding._near_rotation_polar``).

    Args:
        linear: ``(..., 3, 3)`` float64 matrices.
        tolerance: The largest ``||A^T A - I||_F`` accepted (0 < tolerance < 1).

    Returns:
        None when the kernel did not run (the caller runs the numpy twin); else ``(rotation, det)``:
        the ``(..., 3, 3)`` polar rotations and ``(...)`` determinants, or ``(None, None)`` when some
        matrix is farther from a rotation or mirrored (the caller takes the SVD and reports the worst).
    """
    count = int(np.prod(linear.shape[:-2]))
    compiled = _wanted(count)
    if compiled is None or not 0 < tolerance < 1:
        return None
    import warp as wp

    source = _array(np.asarray(linear, dtype=np.float64).reshape(-1, 3, 3), wp.mat33d)
    rotation, det = np.empty((count, 3, 3)), np.empty(count)
    ok = np.empty(count, dtype=np.int32)
    out, dets, flags = _array(rotation, wp.mat33d), _array(det, wp.float64), _array(ok, wp.int32)

    def launch(start: int, stop: int) -> None:
        wp.launch(compiled.near_rotation_polar, dim=stop - start,
                  inputs=[source[start:stop], float(tolerance)],
                  outputs=[out[start:stop], dets[start:stop], flags[start:stop]],
                  device="cpu")

    split_work(count, launch)
    if not ok.all():
        return None, None
    return rotation.reshape(linear.shape), det.reshape(linear.shape[:-2])


def encode_cross_matrix(matrices: np.ndarray, tolerance: float) -> Optional[np.ndarray]:
    """crossMatrix channel values of matrices that all lie within ``tolerance`` of a rotation (kernel
    twin of ``encoding.encode_bones`` for crossMatrix, by way of :func:`near_rotation_polar`).

    Args:
        matrices: ``(..., 4, 4)`` float64 column-vector matrices.
        tolerance: The largest ``||A^T A - I||_F`` accepted (0 < tolerance < 1).

    Returns:
        ``(..., 3, 4)`` float64 values, or None: the kernel did not run, or some matrix is not
        finite, mirrored or farther from a rotation (the numpy twin then finds and reports it).
    """
    count = int(np.prod(matrices.shape[:-2]))
    compiled = _wanted(count)
    if compiled is None or not 0 < tolerance < 1:
        return None
    import warp as wp

    source = _array(np.asarray(matrices, dtype=np.float64).reshape(-1, 4, 4), wp.mat44d)
    values = np.empty((count, 12))
    ok = np.empty(count, dtype=np.int32)
    out, flags = _array(values, wp.float64), _array(ok, wp.int32)

    def launch(start: int, stop: int) -> None:
        wp.launch(compiled.encode_cross_matrix, dim=stop - start, inputs=[source[start:stop], float(tolerance)],
                  outputs=[out[start:stop], flags[start:stop]], device="cpu")

    split_work(count, launch)
    return values.reshape(matrices.shape[:-2] + (3, 4)) if ok.all() else None


def skinning_transforms(translations: np.ndarray, rotations: np.ndarray, scales: np.ndarray,
                        anim_joint: np.ndarray, rest: Optional[np.ndarray], parents: np.ndarray,
                        inverse_bind: np.ndarray, world: Optional[np.ndarray]) -> Optional[np.ndarray]:
    """UsdSkel's skinning transforms of every frame (kernel twin of ``AllFramesSkinning.compute``).

    Args:
        translations: ``(F, A, 3)`` float32 animation translations.
        rotations: ``(F, A, 4)`` float32 quaternions (i, j, k, real), not normalized (as UsdSkel).
        scales: ``(F, A, 3)`` float16 scales.
        anim_joint: ``(J,)`` the animation joint of each skeleton joint, -1 for its rest transform.
        rest: ``(J, 4, 4)`` row-vector rest local transforms, or None (every joint animated).
        parents: ``(J,)`` parent indices, parents first (-1: root).
        inverse_bind: ``(J, 4, 4)`` row-vector inverse world bind transforms.
        world: ``(4, 4)`` row-vector skeleton local-to-world, or None (skeleton space).

    Returns:
        ``(F, J, 4, 4)`` float64 column-vector skinning matrices, or None (run the numpy twin).
    """
    frames, joint_count = translations.shape[0], parents.size
    compiled = _wanted(frames * joint_count)
    if compiled is None:
        return None
    import warp as wp

    if rest is None:
        rest = np.tile(np.eye(4), (joint_count, 1, 1))
    world = np.eye(4) if world is None else np.asarray(world, dtype=np.float64)
    args = [_array(np.asarray(translations, np.float32), wp.vec3f),
            _array(np.asarray(rotations, np.float32), wp.vec4f),
            _array(np.asarray(scales, np.float16).astype(np.float32), wp.vec3f)]
    fixed = [_array(np.asarray(anim_joint, np.int32), wp.int32),
             _array(np.asarray(rest, np.float64)[:, :3, :3], wp.mat33d),
             _array(np.asarray(rest, np.float64)[:, 3, :3], wp.vec3d),
             _array(np.asarray(parents, np.int32), wp.int32),
             _array(np.asarray(inverse_bind, np.float64)[:, :3, :3], wp.mat33d),
             _array(np.asarray(inverse_bind, np.float64)[:, 3, :3], wp.vec3d),
             wp.mat33d(*world[:3, :3].reshape(-1).tolist()), wp.vec3d(*world[3, :3].tolist())]
    out = np.empty((frames, joint_count, 4, 4))
    out_array = _array(out, wp.mat44d)

    def launch(start: int, stop: int) -> None:
        wp.launch(compiled.skinning_transforms, dim=stop - start,
                  inputs=[a[start:stop] for a in args] + fixed,
                  outputs=[out_array[start:stop]], device="cpu")

    split_work(frames, launch)
    return out


def bone_box_bounds(values: np.ndarray, rows: tuple, encoding: str, bones: np.ndarray,
                    center: np.ndarray, half: np.ndarray) -> Optional[tuple]:
    """The bones' boxes over sample times (kernel twin of ``decoders.bounds._bone_box_bounds``).

    Args:
        values: ``(rows, B, T, 4)`` channel values of the whole texture: the stored float16 or
            float32 values as they are, or dequantized float64.
        rows: ``(row0, row1, blend)`` per sample time: texture rows and the weight of ``row1``.
        encoding: A key of :data:`ENCODING_IDS`.
        bones: ``(A,)`` the bones that move points.
        center: ``(A, 3)`` their rest boxes' centers.
        half: ``(A, 3)`` their rest boxes' half sizes.

    Returns:
        ``(low (3,), high (3,), curvature (3,))``: the box of every bone's transformed box at every
        sample, and the largest second difference of any box corner between consecutive samples;
        or None (run the numpy twin).
    """
    row0, row1, blend = rows
    compiled = _wanted(len(blend) * len(bones))
    if compiled is None or encoding not in ENCODING_IDS or len(blend) == 0:
        return None
    import warp as wp

    stored_types = {np.dtype(np.float16): wp.float16, np.dtype(np.float32): wp.float32}
    kind = stored_types.get(np.asarray(values).dtype, wp.float64)
    data = np.ascontiguousarray(values, dtype=None if kind is not wp.float64 else np.float64)
    per_bone = int(np.prod(data.shape[2:]))
    data = _array(data.reshape(data.shape[0], -1), kind)
    inputs = [data, per_bone, _array(np.asarray(row0, np.int32), wp.int32),
              _array(np.asarray(row1, np.int32), wp.int32),
              _array(np.asarray(blend, np.float64), wp.float64), ENCODING_IDS[encoding]]
    bone_array = _array(np.asarray(bones, np.int32), wp.int32)
    center_array = _array(np.asarray(center, np.float64), wp.vec3d)
    half_array = _array(np.asarray(half, np.float64), wp.vec3d)
    low, high, curvature = (np.empty((len(bones), 3)) for _ in range(3))
    outputs = [_array(low, wp.vec3d), _array(high, wp.vec3d), _array(curvature, wp.vec3d)]

    def launch(start: int, stop: int) -> None:
        wp.launch(compiled.bone_box_bounds, dim=stop - start,
                  inputs=inputs + [bone_array[start:stop], center_array[start:stop], half_array[start:stop]],
                  outputs=[o[start:stop] for o in outputs], device="cpu")

    split_work(len(bones), launch, grain=1)  # a bone's samples are a loop in its thread: few, long items
    return low.min(axis=0), high.max(axis=0), curvature.max(axis=0)


def skin_lbs(linear: np.ndarray, translation: np.ndarray, normal: np.ndarray, points: np.ndarray,
             indices: np.ndarray, weights: np.ndarray, normals: Optional[np.ndarray],
             normal_indices: np.ndarray, normal_weights: np.ndarray,
             normalize_normals: bool = True) -> Optional[tuple]:
    """Linear blend skinning in float64 (kernel twin of ``decoders.reference.skin`` for LBS).

    Args:
        linear: ``(n, B, 3, 3)`` decoded linear parts (column-vector, ``p' = A p + t``).
        translation: ``(n, B, 3)``.
        normal: ``(n, B, 3, 3)`` the matrices normals are multiplied by.
        points: ``(V, 3)`` rest points.
        indices: ``(V, K)`` bone indices.
        weights: ``(V, K)`` weights.
        normals: ``(V', 3)`` rest normals, or None.
        normal_indices: ``(V', K)`` bone indices of each normal.
        normal_weights: ``(V', K)`` their weights.
        normalize_normals: Whether the skinned normals are normalized.

    Returns:
        ``(points (n, V, 3), normals (n, V', 3) or None)`` float64, or None (run the numpy twin).
    """
    n, vertex_count = linear.shape[0], points.shape[0]
    compiled = _wanted(n * vertex_count)
    if compiled is None:
        return None
    import warp as wp

    k = indices.shape[1]
    decoded = [_array(np.asarray(linear, np.float64), wp.mat33d), _array(np.asarray(translation, np.float64), wp.vec3d)]
    out_points = np.empty((n, vertex_count, 3))
    point_args = [_array(np.asarray(points, np.float64), wp.vec3d), _array(np.asarray(indices, np.int32), wp.int32),
                  _array(np.asarray(weights, np.float64), wp.float64), k]
    out_array = _array(out_points, wp.vec3d)
    out_normals = None
    if normals is not None:
        out_normals = np.empty((n, normals.shape[0], 3))
        normal_args = [_array(np.asarray(normal, np.float64), wp.mat33d),
                       _array(np.asarray(normals, np.float64), wp.vec3d),
                       _array(np.asarray(normal_indices, np.int32), wp.int32),
                       _array(np.asarray(normal_weights, np.float64), wp.float64), k, int(bool(normalize_normals))]
        normals_array = _array(out_normals, wp.vec3d)

    def launch(start: int, stop: int) -> None:
        wp.launch(compiled.skin_points_lbs, dim=(n, stop - start), inputs=decoded + [start] + point_args,
                  outputs=[out_array], device="cpu")

    def launch_normals(start: int, stop: int) -> None:
        wp.launch(compiled.skin_normals_lbs, dim=(n, stop - start), inputs=[start] + normal_args,
                  outputs=[normals_array], device="cpu")

    split_work(vertex_count, launch)
    if normals is not None:
        split_work(normals.shape[0], launch_normals)
    return out_points, out_normals


def _main() -> int:
    """Compile the kernels into warp's cache now (``python -m vbusd.kernels.bake``)."""

    if not available():
        why = _state.get("why", "warp's CPU backend is not available")
        print(f"vbusd.kernels.bake: the kernels cannot run here ({why}); conversions use numpy", file=sys.stderr)
        return 1
    print("vbusd.kernels.bake: the kernels are in warp's kernel cache", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(_main())

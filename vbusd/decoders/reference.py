"""The numpy reference decoder: clip timing, row interpolation, decoding and skinning.

This is the executable definition of the spec's "Clips", "Interpolation between rows",
"Skinning" (crossfades included) and "Instancing" sections, in float64. The warp kernels (vbusd.decoders.warp) are its
twins and are tested against it.

Times passed here are *clip-local* seconds ``tau`` (0 is the clip's first row), unless a function
says otherwise. The source time of ``tau`` is ``clip.start_time + tau``.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np

from vbusd.format.encoding import BoneTransforms, decode_bones, dequantize, unpack
from vbusd.format.layout import Encoding
from vbusd.format.model import BoundMesh, Clip, Crowd, VirtualBones
from vbusd.format.quaternion import matrix_to_quat, quat_conjugate, quat_multiply, quat_to_matrix
from vbusd.format.errors import InputError, OptionsError
from vbusd.format.rootmotion import displacement
from vbusd.format.motion import crossed_markers, instance_blend

__all__ = ["row_position", "channel_values", "interpolated_values", "bone_transforms", "skin",
           "DENSE_BONE_LIMIT", "normal_point_indices", "skin_mesh", "skin_mesh_at_rows",
           "instance_time", "crossfade", "skin_mesh_crossfade", "skin_crowd", "skinning_matrices",
           "joint_transforms", "crowd_joint_transforms", "bone_order", "decompose_trs", "compose_trs", "slerp",
           "mix_local", "add_local", "mask_weights", "layered_skinning", "skin_mesh_layered", "instance_layers",
           "Additive", "crowd_events", "instance_blend_points", "blends_as_layers",
           "DEFAULT_FRAME_INTERVAL", "check_frame_interval", "hold_reset", "skin_crowd_previous",
           "root_motion_crowd", "check_root_motion_scales"]


def row_position(clip: Clip, tau) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows and blend factor of a clip at clip-local times.

    Args:
        clip: The clip.
        tau: Clip-local times in seconds (scalar or array).

    Returns:
        (i0, i1, f): clip-relative row indices and the weight of ``i1``; the value at ``tau`` is
        ``(1 - f) * row[i0] + f * row[i1]``. Looping clips wrap (row N-1 blends into row 0);
        clamped clips hold their first and last rows.
    """
    n = clip.row_count
    x = np.asarray(tau, dtype=np.float64) * clip.rows_per_second
    if clip.loop:
        x = np.mod(x, n)
        i0 = np.minimum(np.floor(x).astype(np.int64), n - 1)
        return i0, (i0 + 1) % n, x - i0
    x = np.clip(x, 0.0, n - 1)
    i0 = np.floor(x).astype(np.int64)
    return i0, np.minimum(i0 + 1, n - 1), x - i0


def channel_values(vb: VirtualBones) -> np.ndarray:
    """Dequantized float64 channel values (rows, B, T, 4) of the texture's data texels."""
    stored = unpack(vb.texels, vb.layout)
    return dequantize(stored, vb.layout.texel_format, vb.unorm_ranges)


def interpolated_values(vb: VirtualBones, clip_index: int, tau, values: Optional[np.ndarray] = None) -> np.ndarray:
    """Channel values (n, B, T, 4) of every bone at clip-local times, interpolated between rows.

    Args:
        vb: The baked animation.
        clip_index: Index into ``vb.clips``.
        tau: Clip-local times (s).
        values: :func:`channel_values` of ``vb``, to avoid recomputing it.
    """
    clip = vb.clips[clip_index]
    i0, i1, f = row_position(clip, np.atleast_1d(tau))
    if values is None:  # only the rows needed, not the whole texture
        stored = unpack(vb.texels, vb.layout)
        row0 = dequantize(stored[clip.first_row + i0], vb.layout.texel_format, vb.unorm_ranges)
        row1 = dequantize(stored[clip.first_row + i1], vb.layout.texel_format, vb.unorm_ranges)
    else:
        row0 = values[clip.first_row + i0]
        row1 = values[clip.first_row + i1]
    f = f[:, None, None, None]
    if vb.layout.encoding is Encoding.COMPACT_QUAT_TRANSLATION:
        # Compact texels are canonical per row (spec 5.6.4), not hemisphere-continuous as
        # quatTranslation's: the second row's quaternion is negated where the two disagree.
        row1 = np.array(row1, dtype=np.float64, copy=True)
        opposite = np.einsum("...c,...c->...", row0[..., 0, :], row1[..., 0, :]) < 0
        row1[..., 0, :][opposite] *= -1.0
    return (1.0 - f) * row0 + f * row1


def bone_transforms(vb: VirtualBones, clip_index: int, tau) -> BoneTransforms:
    """Decoded bone transforms (n, B, ...) at clip-local times."""
    return decode_bones(interpolated_values(vb, clip_index, tau), vb.layout.encoding)


def _normalize(v: np.ndarray) -> np.ndarray:
    length = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(length > 0, length, 1.0)


def skin(transforms: BoneTransforms, encoding: Encoding | str, points: np.ndarray,
         bone_indices: np.ndarray, bone_weights: np.ndarray,
         normals: Optional[np.ndarray] = None,
         normal_points: Optional[np.ndarray] = None, *,
         normalize_normals: bool = True) -> tuple[np.ndarray, Optional[np.ndarray]]:
    """Skin rest points (and normals) with decoded bone transforms.

    Linear blend skinning for crossMatrix, affineMatrix and quatTranslation:
    ``p' = sum_i w_i (A_i p + t_i)``, ``n' = normalize(sum_i w_i N_i n)``. Dual-quaternion
    skinning for dualQuat (signs relative to the first influence).

    Args:
        transforms: (n, B, ...) decoded transforms.
        encoding: Their encoding (picks LBS or DQS).
        points: (V, 3) rest points.
        bone_indices: (V, K) indices.
        bone_weights: (V, K) weights.
        normals: (V', 3) rest normals or None.
        normal_points: (V',) point index of each normal (faceVarying normals), None when V' = V.
        normalize_normals: False returns the skinned normals before normalization (``sum_i w_i N_i n``
            for LBS), what a crossfade (spec "Crossfade") blends.

    Returns:
        (points (n, V, 3), normals (n, V', 3) or None), float64.
    """
    encoding = Encoding(encoding)
    p = np.asarray(points, dtype=np.float64)
    idx = np.asarray(bone_indices, dtype=np.int64)
    w = np.asarray(bone_weights, dtype=np.float64)
    nidx = idx if normal_points is None else idx[normal_points]
    nw = w if normal_points is None else w[normal_points]
    finish = _normalize if normalize_normals else (lambda v: v)
    if encoding is Encoding.DUAL_QUAT:
        return _skin_dqs(transforms, p, idx, w, normals, nidx, nw, finish)
    # LBS is linear in the transforms, so blend each vertex's matrices first, then transform the
    # point once: sum_k w_k [A|t]_k is one (V, used bones) x (used bones, 12) product per time.
    used, weight_matrix = _weight_matrix(idx, w)
    if used.size > DENSE_BONE_LIMIT:  # many bones: one (n, V, 3, 3) gather per influence slot
        return _skin_lbs_by_slot(transforms, p, idx, w, normals, nidx, nw, finish)
    n = transforms.linear.shape[0]
    affine = np.concatenate([transforms.linear[:, used], transforms.translation[:, used, :, None]], axis=-1)
    blended = np.matmul(weight_matrix, affine.reshape(n, used.size, 12)).reshape(n, -1, 3, 4)
    out_points = _apply(blended[..., :3], p) + blended[..., 3]
    out_normals = None
    if normals is not None:
        rows = weight_matrix if normal_points is None else weight_matrix[normal_points]
        blended_normals = np.matmul(rows, transforms.normal[:, used].reshape(n, used.size, 9)).reshape(n, -1, 3, 3)
        out_normals = finish(_apply(blended_normals, np.asarray(normals, dtype=np.float64)))
    return out_points, out_normals


DENSE_BONE_LIMIT = 64
"""Meshes using at most this many bones are skinned with a dense weight matrix (faster: one BLAS
product instead of K gathers); others one influence slot at a time. Both compute the same sum."""


def _weight_matrix(indices: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The bones a mesh uses and its (V, used bones) weight matrix (repeated indices add up)."""
    used, local = np.unique(indices, return_inverse=True)
    local = local.reshape(indices.shape)
    matrix = np.zeros((indices.shape[0], used.size))
    np.add.at(matrix, (np.arange(indices.shape[0])[:, None], local), weights)
    return used, matrix


def _apply(matrices: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """(n, V, 3, 3) @ (V, 3) per vertex, as three fused multiply-adds (einsum is ~3x slower here)."""
    return (matrices[..., 0] * vectors[None, :, 0, None] + matrices[..., 1] * vectors[None, :, 1, None]
            + matrices[..., 2] * vectors[None, :, 2, None])


def _skin_lbs_by_slot(transforms, p, idx, w, normals, nidx, nw, finish=None):
    finish = _normalize if finish is None else finish
    n = transforms.linear.shape[0]
    linear = np.zeros((n, p.shape[0], 3, 3))
    translation = np.zeros((n, p.shape[0], 3))
    for slot in range(idx.shape[1]):
        linear += transforms.linear[:, idx[:, slot]] * w[None, :, slot, None, None]
        translation += transforms.translation[:, idx[:, slot]] * w[None, :, slot, None]
    out_points = _apply(linear, p) + translation
    out_normals = None
    if normals is not None:
        blended = np.zeros((n, nidx.shape[0], 3, 3))
        for slot in range(nidx.shape[1]):
            blended += transforms.normal[:, nidx[:, slot]] * nw[None, :, slot, None, None]
        out_normals = finish(_apply(blended, np.asarray(normals, dtype=np.float64)))
    return out_points, out_normals


def _blend_dual_quats(transforms: BoneTransforms, idx: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    real = transforms.dual_real[:, idx]  # (n, V, K, 4)
    dual = transforms.dual_dual[:, idx]
    dots = np.einsum("nvkc,nvc->nvk", real, real[:, :, 0, :])
    sign = np.where(dots < 0, -1.0, 1.0) * w[None]
    blend_real = np.einsum("nvkc,nvk->nvc", real, sign)
    blend_dual = np.einsum("nvkc,nvk->nvc", dual, sign)
    norm = np.linalg.norm(blend_real, axis=-1, keepdims=True)
    return blend_real / norm, blend_dual / norm


def _skin_dqs(transforms, p, idx, w, normals, nidx, nw, finish=None):
    finish = _normalize if finish is None else finish
    real, dual = _blend_dual_quats(transforms, idx, w)
    rotation = quat_to_matrix(real)
    translation = 2.0 * quat_multiply(dual, real * np.array([-1.0, -1.0, -1.0, 1.0]))[..., :3]
    out_points = np.einsum("nvij,vj->nvi", rotation, p) + translation
    out_normals = None
    if normals is not None:
        nreal, _ = _blend_dual_quats(transforms, nidx, nw)
        out_normals = finish(np.einsum("nvij,vj->nvi", quat_to_matrix(nreal),
                                       np.asarray(normals, dtype=np.float64)))
    return out_points, out_normals


def normal_point_indices(mesh: BoundMesh) -> Optional[np.ndarray]:
    """Point index of each normal: None for vertex normals, the face-vertex indices for faceVarying."""
    if mesh.normals is None or mesh.normals_interpolation != "faceVarying":
        return None
    return np.asarray(mesh.face_vertex_indices, dtype=np.int64)


def skin_mesh(vb: VirtualBones, mesh: BoundMesh, clip_index: int, tau) -> tuple[np.ndarray, Optional[np.ndarray]]:
    """Skinned points (n, V, 3) and normals of a bound mesh at clip-local times (float64).

    Args:
        vb: The baked animation.
        mesh: One of ``vb.meshes`` (or any mesh bound to ``vb``'s bones).
        clip_index: Index into ``vb.clips``.
        tau: Clip-local times in seconds.
    """
    transforms = bone_transforms(vb, clip_index, tau)
    return skin(transforms, vb.layout.encoding, mesh.points, mesh.bone_indices, mesh.bone_weights,
                mesh.normals, normal_point_indices(mesh))


def skin_mesh_at_rows(vb: VirtualBones, mesh: BoundMesh, clip_index: int) -> tuple[np.ndarray, Optional[np.ndarray]]:
    """Skinned points and normals at every row of a clip (tau = row / rowsPerSecond)."""
    clip = vb.clips[clip_index]
    return skin_mesh(vb, mesh, clip_index, np.arange(clip.row_count) / clip.rows_per_second)


def instance_time(crowd: Crowd, t: float) -> np.ndarray:
    """Clip-local time of every instance at scene time ``t``: timeOffset + playbackRate * t."""
    return np.asarray(crowd.time_offset, dtype=np.float64) + np.asarray(crowd.playback_rate, dtype=np.float64) * t


def crowd_events(vb: VirtualBones, crowd: Crowd, t0: float, t1: float) -> list:
    """The markers every instance of a crowd crosses between scene times ``t0`` and ``t1`` (spec 23.5):
    instance ``i`` plays clip-local time ``timeOffset + playbackRate x t``, so its events are its
    clip's markers crossed from that time at ``t0`` to that at ``t1`` (backward for a negative rate).

    An instance that plays a blend space (spec 23.7) reports the markers of its first weighted
    point's clip at that point's clip time.

    Returns:
        ``[(instance, {"name", "time"})]``, instance by instance, each in the order crossed.
    """
    if crowd.blended:
        crowd = blends_as_layers(vb, crowd)
    out = []
    start, end = instance_time(crowd, t0), instance_time(crowd, t1)
    for i in range(crowd.instance_count):
        clip = vb.clips[int(crowd.clip[i])]
        out.extend((i, event) for event in crossed_markers(vb.markers, clip.name, clip.duration, clip.loop,
                                                           float(start[i]), float(end[i])))
    return out


def crossfade(pose_a: tuple, pose_b: tuple, weight) -> tuple[np.ndarray, Optional[np.ndarray]]:
    """Blend two skinned poses with the weight of the second (spec: "Crossfade").

    ``p' = (1 - w) p_a + w p_b`` and ``n' = normalize((1 - w) n_a + w n_b)``, with the normals
    *before* normalization (:func:`skin` with ``normalize_normals=False``). ``w`` is clamped to
    [0, 1]; where it is 0 the result is exactly pose a, normalized.

    Args:
        pose_a: (points (n, V, 3), unnormalized normals (n, V', 3) or None) of the first clip.
        pose_b: The same of the fade clip.
        weight: Weight of ``pose_b``: a scalar or one per pose (n,).

    Returns:
        (points (n, V, 3), unit normals (n, V', 3) or None), float64.
    """
    w = np.clip(np.asarray(weight, dtype=np.float64), 0.0, 1.0)
    w = np.broadcast_to(w.reshape(-1) if w.ndim else w, (pose_a[0].shape[0],))
    points = _blend(pose_a[0], pose_b[0], w)
    normals = None if pose_a[1] is None else _normalize(_blend(pose_a[1], pose_b[1], w))
    return points, normals


def _blend(a: np.ndarray, b: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """``(1 - w) a + w b`` with one weight per leading entry (spec "Crossfade"): poses or matrices."""
    w = np.asarray(weight, dtype=np.float64).reshape((-1,) + (1,) * (np.ndim(a) - 1))
    return (1.0 - w) * a + w * b


def _per_instance(crowd: Crowd, t: float, evaluate) -> list:
    """Every instance's values at its clip and clip-local time, its fade clip blended in where its
    fade weight is above 0 (spec "Crossfade"). ``evaluate(clip, taus)`` returns a tuple of arrays
    with one entry per time (an entry may be None); the result has one row per instance."""
    taus = instance_time(crowd, t)
    clip_ids = np.asarray(crowd.clip, dtype=np.int64)
    n = crowd.instance_count
    out = None
    for clip_index in np.unique(clip_ids):
        chosen = np.flatnonzero(clip_ids == clip_index)
        parts = evaluate(int(clip_index), taus[chosen])
        if out is None:
            out = [None if part is None else np.empty((n,) + part.shape[1:]) for part in parts]
        for whole, part in zip(out, parts):
            if whole is not None:
                whole[chosen] = part
    if crowd.crossfades:
        fade_clip, fade_offset, fade_rate, fade_weight = crowd.fade_arrays()
        fade_weight = np.clip(fade_weight, 0.0, 1.0)
        fade_taus = fade_offset + fade_rate * t
        for clip_index in np.unique(fade_clip[fade_weight > 0]):
            chosen = np.flatnonzero((fade_clip == clip_index) & (fade_weight > 0))
            faded = evaluate(int(clip_index), fade_taus[chosen])
            for whole, part in zip(out, faded):
                if whole is not None:
                    whole[chosen] = _blend(whole[chosen], part, fade_weight[chosen])
    return out


def _raw_pose(vb: VirtualBones, mesh: BoundMesh, clip_index: int, tau, values=None):
    transforms = decode_bones(interpolated_values(vb, clip_index, np.atleast_1d(tau), values), vb.layout.encoding)
    return skin(transforms, vb.layout.encoding, mesh.points, mesh.bone_indices, mesh.bone_weights,
                mesh.normals, normal_point_indices(mesh), normalize_normals=False)


def skin_mesh_crossfade(vb: VirtualBones, mesh: BoundMesh, clip_index: int, tau, fade_clip: int, fade_tau,
                        fade_weight) -> tuple[np.ndarray, Optional[np.ndarray]]:
    """Skinned points and normals of a bound mesh crossfading two clips (spec: "Crossfade").

    Clip ``clip_index`` plays at clip-local times ``tau`` and clip ``fade_clip`` at ``fade_tau`` (as
    many times as ``tau``), blended with weight ``fade_weight`` of the fade clip. Every encoding
    blends the two skinned poses; for the LBS encodings that equals blending each bone's two
    skinning matrices.

    Args:
        vb: The baked animation.
        mesh: A bound mesh.
        clip_index: Index of the first clip.
        tau: Its clip-local times (n,).
        fade_clip: Index of the fade clip.
        fade_tau: The fade clip's clip-local times (n,).
        fade_weight: Weight of the fade clip, scalar or (n,), clamped to [0, 1].

    Returns:
        (points (n, V, 3), normals (n, V', 3) or None), float64.
    """
    values = channel_values(vb)
    tau = np.atleast_1d(np.asarray(tau, dtype=np.float64))
    fade_tau = np.broadcast_to(np.atleast_1d(np.asarray(fade_tau, dtype=np.float64)), tau.shape)
    pose_a = _raw_pose(vb, mesh, clip_index, tau, values)
    pose_b = _raw_pose(vb, mesh, fade_clip, fade_tau, values)
    return crossfade(pose_a, pose_b, fade_weight)


def skin_crowd(vb: VirtualBones, mesh: BoundMesh, crowd: Crowd, t: float) -> tuple[np.ndarray, Optional[np.ndarray]]:
    """World-space points (N, V, 3) and normals of every instance of ``mesh`` at scene time ``t``.

    Each instance is skinned at its own clip and clip-local time (crossfaded with its fade clip at
    its own time where its fade weight is above 0, spec "Crossfade"), then placed by the point
    instancer's transform: scale, then orientation, then position. Time-sampled fade primvars are
    evaluated at ``t`` (:meth:`~vbusd.format.model.Crowd.at`).
    """
    crowd = crowd.at(t)
    values = channel_values(vb)
    n = crowd.instance_count
    if n == 0:
        return np.empty((0,) + mesh.points.shape), None if mesh.normals is None else np.empty((0,) + mesh.normals.shape)
    if crowd.layered or crowd.blended:
        points, normals = _layered_instances(vb, mesh, crowd, t)
    else:
        points, normals = _per_instance(crowd, t, lambda clip, taus: _raw_pose(vb, mesh, clip, taus, values))
    if normals is not None:
        normals = _normalize(normals)
    rotation = quat_to_matrix(_normalize(np.asarray(crowd.orientations, dtype=np.float64)))
    scale = np.ones((n, 3)) if crowd.scales is None else np.asarray(crowd.scales, dtype=np.float64)
    world = np.einsum("nij,nvj->nvi", rotation, points * scale[:, None, :])
    world += np.asarray(crowd.positions, dtype=np.float64)[:, None, :]
    if normals is not None:
        normals = _normalize(np.einsum("nij,nvj->nvi", rotation, normals / scale[:, None, :]))
    return world, normals


def skinning_matrices(vb: VirtualBones, clip_index: int, tau) -> np.ndarray:
    """Decoded skinning transforms ``M_b`` (n, B, 4, 4), column vectors, at clip-local times.

    Every encoding decodes to ``[A | t]`` (spec "Encodings"; for dualQuat ``A = R(q_r)`` and
    ``t = 2 (q_d (x) conj(q_r)).xyz``), interpolated between rows as a decoder interpolates them.
    """
    transforms = bone_transforms(vb, clip_index, np.atleast_1d(tau))
    n, b = transforms.linear.shape[:2]
    out = np.zeros((n, b, 4, 4))
    out[..., :3, :3] = transforms.linear
    out[..., :3, 3] = transforms.translation
    out[..., 3, 3] = 1.0
    return out


def _bind(vb: VirtualBones) -> np.ndarray:
    if vb.bind_transforms is None:
        raise InputError("the animation stores no joint bind transforms (vb:bindTransforms, format 1.1): "
                         "reconvert the source with this vbusd to use sockets", location=vb.path,
                         code="socket.noBindTransforms")
    return np.asarray(vb.bind_transforms, dtype=np.float64)


def joint_transforms(vb: VirtualBones, clip_index: int, tau) -> np.ndarray:
    """Every joint's transform in animation space, ``J_b = M_b B_b`` (n, B, 4, 4) (spec "Sockets").

    ``M_b`` is the decoded skinning transform (:func:`skinning_matrices`), ``B_b`` the joint's bind
    transform stored in the asset (``vb.bind_transforms``).

    Raises:
        InputError: The asset stores no bind transforms (code ``socket.noBindTransforms``).
    """
    return skinning_matrices(vb, clip_index, tau) @ _bind(vb)[None]


def crowd_joint_transforms(vb: VirtualBones, crowd: Crowd, bone: int, t: float) -> np.ndarray:
    """World transform (N, 4, 4) of joint ``bone`` of every instance at scene time ``t`` (a crowd's sockets).

    ``P_i ((1 - w) M_a + w M_b) B`` with ``P_i`` the instance placement (scale, orientation,
    position), ``M_a`` and ``M_b`` the decoded transforms of the instance's clip and fade clip at
    their own times and ``w`` its fade weight (spec "Sockets": the matrix crossfade).
    """
    bind = _bind(vb)[bone]
    crowd = crowd.at(t)
    n = crowd.instance_count
    if n == 0:
        return np.empty((0, 4, 4))
    if crowd.layered or crowd.blended:
        # Spec 8.6 and 8.4: each side of the crossfade layered, the two layered transforms blended.
        taus = instance_time(crowd, t)
        fade_clip, fade_offset, fade_rate, fade_weight = crowd.fade_arrays()
        local = np.empty((n, 4, 4))
        for i, layers in enumerate(instance_layers(vb, crowd, t)):
            blend = instance_blend_points(vb, crowd, i, t)
            local[i] = _matrices(layered_skinning(vb, int(crowd.clip[i]), taus[i:i + 1], layers, blend=blend)[0])[0, bone]
            w = float(np.clip(fade_weight[i], 0.0, 1.0)) if crowd.crossfades else 0.0
            if w > 0:
                fade_tau = np.array([fade_offset[i] + fade_rate[i] * t])
                faded = _matrices(layered_skinning(vb, int(fade_clip[i]), fade_tau, layers)[0])[0, bone]
                local[i] = (1.0 - w) * local[i] + w * faded
    else:
        local, = _per_instance(crowd, t, lambda clip, taus: (skinning_matrices(vb, clip, taus)[:, bone],))
    rotation = quat_to_matrix(_normalize(np.asarray(crowd.orientations, dtype=np.float64)))
    scale = np.ones((n, 3)) if crowd.scales is None else np.asarray(crowd.scales, dtype=np.float64)
    placement = np.zeros((n, 4, 4))
    placement[:, :3, :3] = rotation * scale[:, None, :]
    placement[:, :3, 3] = np.asarray(crowd.positions, dtype=np.float64)
    placement[:, 3, 3] = 1.0
    return placement @ local @ bind


def root_motion(vb: VirtualBones, clip_index: int, t0: float, t1: float) -> np.ndarray:
    """The root displacement (4, 4) of a clip baked in place between clip-local times ``t0`` and ``t1``.

    ``D(t1) D(t0)^-1`` of the clip's root track (spec "Root motion"), in the animation's space: the
    source pose at ``t`` is ``D(t)`` applied to the decoded in-place pose, so a character that
    stands at ``D(t0)`` at ``t0`` stands at ``D(t1)`` at ``t1``; looping clips accumulate one
    loop's displacement per period. The identity when the animation has no root track.
    """
    if vb.root_motion is None:
        return np.eye(4)

    return displacement(vb.root_motion, clip_index, vb.clips[clip_index], t0, t1)



def check_root_motion_scales(up_axis: str, scales: np.ndarray, yaw: np.ndarray) -> None:
    """Refuse an instance that its root motion turns (``yaw`` not 0) while its scale differs between
    the two horizontal axes: ``S R_up`` is then no rotation times a scale (the placement shears)."""
    up = 1 if up_axis == "Y" else 2
    horizontal = [axis for axis in range(3) if axis != up]
    shearing = (np.abs(yaw) > 0) & ~np.isclose(scales[:, horizontal[0]], scales[:, horizontal[1]], rtol=1e-12, atol=0)
    if shearing.any():
        i = int(np.flatnonzero(shearing)[0])
        raise OptionsError(f"instance {i} turns with its root motion but its scale {scales[i].tolist()} differs "
                           f"between the horizontal axes", file="root_motion_crowd")


def root_motion_crowd(vb: VirtualBones, crowd: Crowd, t: float, t0: float = 0.0) -> Crowd:
    """The crowd with every instance moved by its root displacement at scene time ``t`` (spec 8.5, 21.1).

    What a runtime that plays root motion draws: instance ``i`` placed by its transform times
    ``D_i = D(tau_i(t)) D(tau_i(t0))^-1``, the root track of its clip (``crowd.clip``; a fade clip's
    track is not blended) between its clip-local times ``timeOffset + playbackRate * t0`` and
    ``timeOffset + playbackRate * t`` (:func:`root_motion`, the web runtimes'
    ``crowd.rootMotionMatrix(i, t0, t)``). ``D_i = T(d) R_up(phi)`` is rigid, so the moved instance
    is again a position, orientation and scale: position ``p + R(q) (s * d)``, orientation
    ``q R_up(phi)``, scale ``s``. Skin the moved crowd at ``t`` for this frame and pass the crowd
    moved at ``t - dt`` as ``previous_crowd`` of :func:`skin_crowd_previous`: the previous pose is
    placed by the previous root displacement, so a walking instance's velocity is its root's speed
    times ``dt`` plus its pose's own change.

    Args:
        vb: The baked animation; without root tracks the crowd is returned unchanged.
        crowd: The instances at their start (scene time ``t0``).
        t: Scene time (s).
        t0: Scene time (s) at which each instance stands at its own transform.

    Returns:
        A :class:`~vbusd.format.model.Crowd` with moved positions and orientations, its other fields
        those of ``crowd``.

    Raises:
        OptionsError: A non-finite time, or an instance turned by its root track whose scale differs
            between the two horizontal axes (its placement would shear, no position-orientation-scale).
    """
    if not (np.isfinite(t) and np.isfinite(t0)):
        raise OptionsError(f"scene times must be finite, got t={t!r}, t0={t0!r}", file="root_motion_crowd")
    if vb.root_motion is None or crowd.instance_count == 0:
        return crowd
    up = 1 if vb.root_motion.up_axis == "Y" else 2
    n = crowd.instance_count
    offsets = np.asarray(crowd.time_offset, dtype=np.float64)
    rates = np.asarray(crowd.playback_rate, dtype=np.float64)
    clips = np.asarray(crowd.clip, dtype=np.int64)
    moves = np.stack([root_motion(vb, int(clips[i]), offsets[i] + rates[i] * t0, offsets[i] + rates[i] * t)
                      for i in range(n)])
    # The yaw of D about the up axis: rotation_about_up puts sin(phi) at [0, 2] (Y up) or [1, 0] (Z up).
    sin = moves[:, 0, 2] if up == 1 else moves[:, 1, 0]
    phi = np.arctan2(sin, moves[:, 0, 0])
    scales = np.ones((n, 3)) if crowd.scales is None else np.asarray(crowd.scales, dtype=np.float64)
    check_root_motion_scales(vb.root_motion.up_axis, scales, phi)
    orientations = _normalize(np.asarray(crowd.orientations, dtype=np.float64))
    rotation = quat_to_matrix(orientations)
    positions = np.asarray(crowd.positions, dtype=np.float64) + np.einsum("nij,nj->ni", rotation,
                                                                          scales * moves[:, :3, 3])
    turn = np.zeros((n, 4))
    turn[:, up] = np.sin(phi / 2)
    turn[:, 3] = np.cos(phi / 2)
    return dataclasses.replace(crowd, positions=positions, orientations=quat_multiply(orientations, turn))

# --------------------------------------------------------------------------------------------
# Layers and bone masks (format 1.2, spec "Layers and bone masks")
# --------------------------------------------------------------------------------------------


def bone_order(parents) -> np.ndarray:
    """Bone indices ordered parents before children (glTF lists skin joints in any order)."""
    parents = np.asarray(parents, dtype=np.int64)
    depth = np.zeros(parents.size, dtype=np.int64)
    for b in range(parents.size):
        node, d = int(parents[b]), 0
        while node != -1:
            node, d = int(parents[node]), d + 1
        depth[b] = d
    return np.argsort(depth, kind="stable")


def decompose_trs(matrices: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Translation, unit quaternion (x, y, z, w) and scale of (..., 4, 4) matrices, as three.js'
    ``Matrix4.decompose``: scale = column lengths (x negated when the determinant is negative),
    rotation = the 3x3 part with its columns divided by the scale."""
    linear = matrices[..., :3, :3]
    scale = np.linalg.norm(linear, axis=-2)
    scale[..., 0] *= np.where(np.linalg.det(linear) < 0, -1.0, 1.0)
    rotation = linear / np.where(scale == 0, 1.0, scale)[..., None, :]
    return matrices[..., :3, 3].copy(), matrix_to_quat(rotation), scale


def compose_trs(translation: np.ndarray, quaternion: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """``T(t) R(q) S(s)`` as (..., 4, 4) matrices."""
    out = np.zeros(translation.shape[:-1] + (4, 4))
    out[..., :3, :3] = quat_to_matrix(quaternion) * scale[..., None, :]
    out[..., :3, 3] = translation
    out[..., 3, 3] = 1.0
    return out


def slerp(q0: np.ndarray, q1: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Shortest-arc spherical interpolation of (..., 4) unit quaternions by (...) weights, as
    three.js' ``Quaternion.slerpFlat`` (the sign of ``q1`` that makes the dot product >= 0; a
    normalized lerp where the two are nearly equal)."""
    cos = np.sum(q0 * q1, axis=-1)
    direction = np.where(cos >= 0, 1.0, -1.0)
    sin_squared = 1.0 - cos * cos
    near = sin_squared <= np.finfo(np.float64).eps
    sin = np.sqrt(np.where(near, 1.0, sin_squared))
    angle = np.arctan2(sin, cos * direction)
    s0 = np.where(near, 1.0 - alpha, np.sin((1.0 - alpha) * angle) / sin)
    s1 = np.where(near, alpha, np.sin(alpha * angle) / sin)
    out = q0 * s0[..., None] + q1 * (s1 * direction)[..., None]
    return np.where(near[..., None], out / np.linalg.norm(out, axis=-1, keepdims=True), out)


def mix_local(x: np.ndarray, y: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """``mix(X, Y, alpha)`` of spec 8.6 for (..., 4, 4) local transforms and (...) weights in [0, 1]:
    X at 0, Y at 1, else translation and scale lerped and rotation slerped."""
    out = np.where((alpha >= 1.0)[..., None, None], y, x)
    partial = (alpha > 0.0) & (alpha < 1.0)
    if np.any(partial):
        a = alpha[partial]
        tx, qx, sx = decompose_trs(x[partial])
        ty, qy, sy = decompose_trs(y[partial])
        out[partial] = compose_trs((1.0 - a)[:, None] * tx + a[:, None] * ty, slerp(qx, qy, a),
                                   (1.0 - a)[:, None] * sx + a[:, None] * sy)
    return out


def add_local(x: np.ndarray, layer: np.ndarray, reference: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """``X`` with ``alpha`` of the additive difference of ``layer`` from ``reference`` (spec 23.4), for
    (..., 4, 4) local transforms and (...) weights: ``t + a (t_L - t_R)``, ``q (x) slerp(1, q_R^-1 q_L, a)``,
    ``s + a (s_L - s_R)``, as three.js' ``makeClipAdditive`` and additive ``PropertyMixer`` give; ``X``
    itself where ``alpha`` is 0."""
    out = x.copy()
    active = alpha > 0.0
    if np.any(active):
        a = np.minimum(alpha[active], 1.0)
        tx, qx, sx = decompose_trs(x[active])
        tl, ql, sl = decompose_trs(layer[active])
        tr, qr, sr = decompose_trs(reference[active])
        delta = quat_multiply(quat_conjugate(qr), ql)
        identity = np.broadcast_to(np.array([0.0, 0.0, 0.0, 1.0]), delta.shape)
        out[active] = compose_trs(tx + a[:, None] * (tl - tr), quat_multiply(qx, slerp(identity, delta, a)),
                                  sx + a[:, None] * (sl - sr))
    return out


class Additive(tuple):
    """The additive mode of a layer (spec 23.4): ``Additive((reference clip, reference times (n,)))``;
    the fifth element of a layer tuple of :func:`layered_skinning` (absent: override)."""


def _local(joints: np.ndarray, parents: np.ndarray) -> np.ndarray:
    """Local transforms ``J_p^-1 J_b`` (a root's is ``J_b``) of (n, B, 4, 4) joint transforms."""
    local = joints.copy()
    child = parents >= 0
    local[:, child] = np.linalg.solve(joints[:, parents[child]], joints[:, child])
    return local


def mask_weights(vb: VirtualBones, mask, *, what: str = "skin") -> np.ndarray:
    """The (B,) weights of a mask given by name or index (spec 8.6).

    Raises:
        InputError: The animation stores no masks, or none of that name (code ``layers.noMask``).
    """

    names = [name for name, _ in vb.masks]
    if isinstance(mask, str) and mask in names:
        return np.asarray(vb.masks[names.index(mask)][1], dtype=np.float64)
    if isinstance(mask, (int, np.integer)) and not isinstance(mask, bool) and 0 <= mask < len(names):
        return np.asarray(vb.masks[int(mask)][1], dtype=np.float64)
    have = f"masks: {', '.join(names)}" if names else "it stores none (format 1.2): reconvert with --mask NAME=BONE"
    raise InputError(f"animation {vb.path} has no bone mask {mask!r} ({have})", file=what, location=vb.path,
                     code="layers.noMask")


def layered_skinning(vb: VirtualBones, clip_index: int, tau, layers, values=None, *,
                     blend=None) -> tuple[BoneTransforms, np.ndarray]:
    """Decoded bone transforms of one clip with layers applied (spec "Layers and bone masks").

    Args:
        vb: The baked animation (with bone parents, bind transforms and masks).
        clip_index: The base clip.
        tau: Its clip-local times (n,).
        layers: ``(clip index, times (n,), weight (scalar or (n,)), mask weights (B,))`` per layer,
            applied in order; an additive layer (spec 23.4) has a fifth element, :class:`Additive`.
        values: :func:`channel_values` of ``vb``, to avoid recomputing it.
        blend: A blend space's points of non-zero weight in the space's order (spec 23.1), as
            ``(clip index, times (n,), weight)``; it replaces ``clip_index`` and ``tau`` as the base.
            One point of weight 1 is that clip alone, bit for bit.

    Returns:
        ``(transforms, joints)``: the :class:`BoneTransforms` to skin with (a bone the layers leave
        unchanged keeps its decoded transform exactly) and the layered joint transforms ``J'``
        (n, B, 4, 4).
    """
    blend = [entry for entry in (blend or ()) if entry[2] > 0.0]
    if len(blend) == 1:
        clip_index, tau = blend[0][0], blend[0][1]
        blend = []
    tau = np.atleast_1d(np.asarray(tau, dtype=np.float64))
    encoding = vb.layout.encoding
    bind = _bind(vb)

    def local_pose(clip, times):
        times = np.broadcast_to(np.atleast_1d(np.asarray(times, dtype=np.float64)), tau.shape)
        joints_of = _matrices(decode_bones(interpolated_values(vb, clip, times, values), encoding)) @ bind[None]
        return _local(joints_of, parents)

    if blend:
        # Spec 23.1: the points' local transforms accumulated in the space's order, as three.js'
        # PropertyMixer accumulates weighted actions.
        parents = np.asarray(vb.bone_parents, dtype=np.int64)
        tau = np.broadcast_to(np.atleast_1d(np.asarray(blend[0][1], dtype=np.float64)), tau.shape).copy()
        base = decode_bones(interpolated_values(vb, blend[0][0], tau, values), encoding)
        local = local_pose(blend[0][0], blend[0][1])
        total = float(blend[0][2])
        for clip, times, weight in blend[1:]:
            total += float(weight)
            local = mix_local(local, local_pose(clip, times), np.full(local.shape[:2], float(weight) / total))
        joints = _matrices(base) @ bind[None]
        changed = np.ones(local.shape[:2], dtype=bool)
    else:
        base = decode_bones(interpolated_values(vb, clip_index, tau, values), encoding)
        joints = _matrices(base) @ bind[None]
        if not layers:
            return base, joints
        parents = np.asarray(vb.bone_parents, dtype=np.int64)
        local = _local(joints, parents)
        changed = np.zeros(local.shape[:2], dtype=bool)
    for layer_entry in layers:
        clip, times, weight, mask = layer_entry[:4]
        w = np.clip(np.broadcast_to(np.asarray(weight, dtype=np.float64), tau.shape), 0.0, 1.0)
        alpha = w[:, None] * np.asarray(mask, dtype=np.float64)[None, :]
        if len(layer_entry) > 4 and isinstance(layer_entry[4], Additive):
            reference_clip, reference_times = layer_entry[4]
            local = add_local(local, local_pose(clip, times), local_pose(reference_clip, reference_times), alpha)
        else:
            local = mix_local(local, local_pose(clip, times), alpha)
        changed |= alpha > 0.0
    layered = joints.copy()
    for b in bone_order(parents):
        p = parents[b]
        if p >= 0:
            changed[:, b] |= changed[:, p]
        rows = changed[:, b]
        if np.any(rows):
            layered[rows, b] = local[rows, b] if p < 0 else layered[rows, p] @ local[rows, b]
    matrices = layered @ np.linalg.inv(bind)[None]
    linear = np.where(changed[..., None, None], matrices[..., :3, :3], base.linear)
    translation = np.where(changed[..., None], matrices[..., :3, 3], base.translation)
    normal = base.normal.copy()
    if np.any(changed):
        normal[changed] = np.swapaxes(np.linalg.inv(linear[changed]), -1, -2)
    real, dual = base.dual_real, base.dual_dual
    if encoding is Encoding.DUAL_QUAT:
        real, dual = real.copy(), dual.copy()
        if np.any(changed):
            q = matrix_to_quat(linear[changed] / np.linalg.norm(linear[changed], axis=-2)[..., None, :])
            real[changed] = q
            dual[changed] = 0.5 * quat_multiply(np.concatenate([translation[changed], np.zeros(q.shape[:-1] + (1,))],
                                                               axis=-1), q)
    return BoneTransforms(linear, translation, normal, real, dual), layered


def _matrices(transforms: BoneTransforms) -> np.ndarray:
    n, b = transforms.linear.shape[:2]
    out = np.zeros((n, b, 4, 4))
    out[..., :3, :3] = transforms.linear
    out[..., :3, 3] = transforms.translation
    out[..., 3, 3] = 1.0
    return out


def skin_mesh_layered(vb: VirtualBones, mesh: BoundMesh, clip_index: int, tau, layers, *, fade_clip=None,
                      fade_tau=None, fade_weight=0.0, blend=None) -> tuple[np.ndarray, Optional[np.ndarray]]:
    """Skinned points and normals of a bound mesh with layers (spec "Layers and bone masks").

    With a fade clip, each side of the crossfade is layered and the two layered poses are blended
    as :func:`skin_mesh_crossfade` blends unlayered ones.

    Args:
        vb: The baked animation.
        mesh: A bound mesh.
        clip_index: The base clip.
        tau: Its clip-local times (n,).
        layers: As :func:`layered_skinning`.
        fade_clip: The fade clip's index, or None.
        fade_tau: Its clip-local times.
        fade_weight: Its weight (clamped to [0, 1]).
        blend: A blend space's weighted points, as :func:`layered_skinning` takes them (spec 23.1);
            the base instead of ``clip_index`` and ``tau`` (not with a fade clip).

    Returns:
        (points (n, V, 3), normals (n, V', 3) or None), float64.
    """
    values = channel_values(vb)
    tau = np.atleast_1d(np.asarray(tau, dtype=np.float64))

    def pose(clip, times, finish):
        transforms, _ = layered_skinning(vb, clip, times, layers, values, blend=None if fade_clip is not None else blend)
        return skin(transforms, vb.layout.encoding, mesh.points, mesh.bone_indices, mesh.bone_weights,
                    mesh.normals, normal_point_indices(mesh), normalize_normals=finish)

    if fade_clip is None:
        return pose(clip_index, tau, True)
    fade_tau = np.broadcast_to(np.atleast_1d(np.asarray(fade_tau, dtype=np.float64)), tau.shape)
    return crossfade(pose(clip_index, tau, False), pose(fade_clip, fade_tau, False), fade_weight)


def instance_layers(vb: VirtualBones, crowd: Crowd, t: float) -> list:
    """Each instance's layers at scene time ``t`` as :func:`layered_skinning` takes them (spec 15,
    ``primvars:vb:layer*``): layers of weight 0 are left out."""
    if crowd.layer_weight is None:
        return [[] for _ in range(crowd.instance_count)]
    weight = np.asarray(crowd.layer_weight, dtype=np.float64)
    clip = np.asarray(crowd.layer_clip, dtype=np.int64).reshape(weight.shape)
    offset = np.asarray(crowd.layer_time_offset, dtype=np.float64).reshape(weight.shape)
    rate = np.asarray(crowd.layer_playback_rate, dtype=np.float64).reshape(weight.shape)
    mask = np.asarray(crowd.layer_mask, dtype=np.int64).reshape(weight.shape)
    # Format 1.3 (spec 23.4): additive layers and their reference poses (default: the layer's clip at 0).
    mode = (np.zeros(weight.shape, np.int64) if crowd.layer_mode is None
            else np.asarray(crowd.layer_mode, dtype=np.int64).reshape(weight.shape))
    reference_clip = (clip if crowd.layer_reference_clip is None
                      else np.asarray(crowd.layer_reference_clip, dtype=np.int64).reshape(weight.shape))
    reference_time = (np.zeros(weight.shape) if crowd.layer_reference_time is None
                      else np.asarray(crowd.layer_reference_time, dtype=np.float64).reshape(weight.shape))

    def layer(i, j):
        entry = (int(clip[i, j]), np.array([offset[i, j] + rate[i, j] * t]), float(np.clip(weight[i, j], 0.0, 1.0)),
                 mask_weights(vb, int(mask[i, j])))
        if mode[i, j] == 1:
            entry += (Additive((int(reference_clip[i, j]), np.array([reference_time[i, j]]))),)
        return entry

    return [[layer(i, j) for j in range(weight.shape[1]) if weight[i, j] > 0] for i in range(weight.shape[0])]


def instance_blend_points(vb: VirtualBones, crowd: Crowd, i: int, t: float):
    """Instance ``i``'s blend space at scene time ``t`` as :func:`layered_skinning` takes it (spec 23.7),
    ``[(clip index, times (1,), weight)]``, or None when it plays its clip.

    Raises:
        InputError: A blend space index the animation does not have, or a blend with a crossfade
            (code ``blend.noSpace``).
    """
    if crowd.blend_space is None or int(crowd.blend_space[i]) < 0:
        return None
    index = int(crowd.blend_space[i])
    if index >= len(vb.blend_spaces):
        raise InputError(f"instance {i} plays blend space {index}, but the animation stores {len(vb.blend_spaces)}",
                         location=f"{crowd.path}.primvars:vb:blendSpace", code="blend.noSpace")
    if crowd.crossfades and float(crowd.fade_arrays()[3][i]) > 0:
        raise InputError(f"instance {i} plays a blend space and a crossfade; a blend is the whole base pose "
                         "(spec 23.7)", location=f"{crowd.path}.primvars:vb:blendSpace", code="blend.noSpace")
    space = vb.blend_spaces[index]
    names = [c.name for c in vb.clips]

    def value(field):
        return 0.0 if field is None else float(np.asarray(field)[i])

    entries = instance_blend(space, value(crowd.blend_x), value(crowd.blend_y), value(crowd.blend_phase),
                             float(np.asarray(crowd.playback_rate)[i]), {c.name: c.duration for c in vb.clips},
                             vb.markers)
    return [(names.index(space.clips[k]), np.array([offset + rate * t]), w) for k, w, _, offset, rate in entries]


def blends_as_layers(vb: VirtualBones, crowd: Crowd) -> Crowd:
    """A crowd whose instances play blend spaces (spec 23.7) as one that plays layers: each blended
    instance plays its first weighted point's clip (offset and rate from :func:`instance_blend`) with
    one override layer per further point, under mask index ``len(vb.masks)`` -- a mask of every bone
    the decoder adds -- before its own layers (spec 23.1, "Decoding a blend as layers"). What a
    decoder that layers (warp) decodes blends with; the times are linear in the scene time, so the
    conversion holds at every time."""
    n = crowd.instance_count
    every = len(vb.masks)
    names = [c.name for c in vb.clips]
    durations = {c.name: c.duration for c in vb.clips}
    own = 0 if crowd.layer_weight is None else np.asarray(crowd.layer_weight).reshape(n, -1).shape[1]
    rows = []
    clip = np.asarray(crowd.clip, np.int32).copy()
    offset = np.asarray(crowd.time_offset, np.float64).copy()
    rate = np.asarray(crowd.playback_rate, np.float64).copy()
    for i in range(n):
        blend = instance_blend_points(vb, crowd, i, 0.0)  # checks the space and the crossfade
        if blend is None:
            rows.append([])
            continue
        space = vb.blend_spaces[int(crowd.blend_space[i])]
        value = lambda field: 0.0 if field is None else float(np.asarray(field)[i])  # noqa: E731
        entries = instance_blend(space, value(crowd.blend_x), value(crowd.blend_y), value(crowd.blend_phase),
                                 float(rate[i]), durations, vb.markers)
        first = entries[0]
        clip[i], offset[i], rate[i] = names.index(space.clips[first[0]]), first[3], first[4]
        rows.append([(names.index(space.clips[k]), o, r, relative, every) for k, _, relative, o, r in entries[1:]])
    extra = max((len(r) for r in rows), default=0)
    count = extra + own
    if count == 0:
        return dataclasses.replace(crowd, blend_space=None, clip=clip, time_offset=offset, playback_rate=rate)
    layer = {key: np.zeros((n, count), dtype) for key, dtype in (("clip", np.int32), ("offset", np.float64),
                                                                 ("rate", np.float64), ("weight", np.float32),
                                                                 ("mask", np.int32), ("mode", np.int32),
                                                                 ("reference_clip", np.int32),
                                                                 ("reference_time", np.float64))}
    for i, row in enumerate(rows):
        for j, (c, o, r, w, m) in enumerate(row):
            layer["clip"][i, j], layer["offset"][i, j], layer["rate"][i, j] = c, o, r
            layer["weight"][i, j], layer["mask"][i, j], layer["reference_clip"][i, j] = w, m, c
    if own:
        shape = (n, own)
        source = {"clip": crowd.layer_clip, "offset": crowd.layer_time_offset, "rate": crowd.layer_playback_rate,
                  "weight": crowd.layer_weight, "mask": crowd.layer_mask, "mode": crowd.layer_mode,
                  "reference_clip": crowd.layer_reference_clip if crowd.layer_reference_clip is not None
                  else crowd.layer_clip, "reference_time": crowd.layer_reference_time}
        for key, values in source.items():
            if values is not None:
                layer[key][:, extra:] = np.asarray(values).reshape(shape)
    return dataclasses.replace(
        crowd, clip=clip, time_offset=offset, playback_rate=rate, blend_space=None, layer_clip=layer["clip"],
        layer_time_offset=layer["offset"], layer_playback_rate=layer["rate"], layer_weight=layer["weight"],
        layer_mask=layer["mask"], layer_mode=layer["mode"], layer_reference_clip=layer["reference_clip"],
        layer_reference_time=layer["reference_time"])


def _layered_instances(vb: VirtualBones, mesh: BoundMesh, crowd: Crowd, t: float):
    """Skinned points and normals (N, V, 3) of a layered or blended crowd, one instance at a time."""
    taus = instance_time(crowd, t)
    fade_clip, fade_offset, fade_rate, fade_weight = crowd.fade_arrays()
    points, normals = [], []
    for i, layers in enumerate(instance_layers(vb, crowd, t)):
        blend = instance_blend_points(vb, crowd, i, t)
        fading = crowd.crossfades and fade_weight[i] > 0 and blend is None
        p, n = skin_mesh_layered(vb, mesh, int(crowd.clip[i]), taus[i:i + 1], layers,
                                 fade_clip=int(fade_clip[i]) if fading else None,
                                 fade_tau=np.array([fade_offset[i] + fade_rate[i] * t]), fade_weight=fade_weight[i],
                                 blend=blend)
        points.append(p[0])
        normals.append(None if n is None else n[0])
    return np.stack(points), None if normals[0] is None else np.stack(normals)


# --------------------------------------------------------------------------------------------
# The previous-frame pose (spec 21)
# --------------------------------------------------------------------------------------------

DEFAULT_FRAME_INTERVAL = 1.0 / 60.0
"""The frame interval ``dt`` (s of scene time) a previous pose takes when none is given (spec 21.1)."""


def check_frame_interval(dt, what: str = "skin") -> float:
    """``dt`` as float seconds; refused (one line naming it) unless finite and above 0 (spec 21.1).

    Raises:
        OptionsError: ``dt`` is not a finite number above 0.
    """
    ok = isinstance(dt, (int, float, np.integer, np.floating)) and not isinstance(dt, (bool, np.bool_))
    value = float(dt) if ok else float("nan")
    if not (np.isfinite(value) and value > 0.0):
        raise OptionsError(f"previous (the frame interval) must be a finite number of seconds above 0, got {dt!r}",
                           file=what)
    return value


def hold_reset(previous: np.ndarray, current: np.ndarray, reset) -> np.ndarray:
    """``previous`` with the rows of reset instances replaced by ``current`` (spec 21.1, Reset).

    The numpy twin of ``warp_kernels.hold_reset_kernel``. ``reset`` is None (no instance reset) or
    one flag per leading entry.
    """
    if reset is None:
        return previous
    flags = np.asarray(reset, dtype=bool).reshape(-1)
    if flags.shape[0] != previous.shape[0]:
        raise OptionsError(f"reset has {flags.shape[0]} flags for {previous.shape[0]} instances", file="previous")
    return np.where(flags.reshape((-1,) + (1,) * (previous.ndim - 1)), current, previous)


def skin_crowd_previous(vb: VirtualBones, mesh: BoundMesh, crowd: Crowd, t: float,
                        dt: float = DEFAULT_FRAME_INTERVAL, *, reset=None,
                        previous_crowd: Optional[Crowd] = None) -> tuple[np.ndarray, Optional[np.ndarray]]:
    """World-space points (N, V, 3) and normals of every instance's previous-frame pose (spec 21).

    Each instance is evaluated at scene time ``t - dt`` by exactly the rules of :func:`skin_crowd`:
    its clip-local time ``timeOffset + playbackRate (t - dt)`` wrapped or clamped as its clip does,
    crossfade and layers (time-sampled ones included) at ``t - dt``. It is placed by
    ``previous_crowd``'s transforms (positions, orientations, scales; its other fields are not read)
    when given, else by ``crowd``'s. A reset instance's previous pose is its current pose.

    Args:
        vb: The baked animation.
        mesh: A bound mesh.
        crowd: The instances.
        t: Scene time (s) of the current frame.
        dt: The frame interval (s), finite and above 0; 1/60 by default.
        reset: None, or one flag per instance: the runtime switched its clip or teleported it this
            frame (its velocity is zero).
        previous_crowd: The instances' transforms of the previous frame, or None.

    Returns:
        (points (N, V, 3), normals or None), float64, in the space of :func:`skin_crowd`'s.
    """
    dt = check_frame_interval(dt, "skin_crowd_previous")
    placed = crowd
    if previous_crowd is not None:
        if previous_crowd.instance_count != crowd.instance_count:
            raise OptionsError(f"previous_crowd has {previous_crowd.instance_count} instances, the crowd "
                               f"{crowd.instance_count}", file="skin_crowd_previous")
        placed = dataclasses.replace(crowd, positions=previous_crowd.positions,
                                     orientations=previous_crowd.orientations, scales=previous_crowd.scales)
    points, normals = skin_crowd(vb, mesh, placed, t - dt)
    if reset is not None and np.any(np.asarray(reset, dtype=bool)):
        now_points, now_normals = skin_crowd(vb, mesh, crowd, t)
        points = hold_reset(points, now_points, reset)
        normals = None if normals is None else hold_reset(normals, now_normals, reset)
    return points, normals

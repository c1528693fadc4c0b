"""The Virtual Bones decoder in warp-lang, on CPU and CUDA: the executable spec, on the device.

:class:`Decoder` uploads one baked animation's texture and one bound mesh to a device once and
keeps them there; each call then computes every instance's clip rows and placement (one launch,
instances), decodes the bones of every instance (one launch, instances x bones) and skins
positions and normals of the whole crowd (one launch, instances x vertices) into float32 device
arrays, with no host<->device copy beyond the kernels' scalar arguments. A renderer or a
simulation can call it every frame::

    decoder = Decoder(vb, vb.meshes[0], device="cuda")
    crowd_on_device = decoder.upload_crowd(crowd)
    out = decoder.allocate(crowd.instance_count)
    for t in frame_times:
        decoder.skin_crowd(crowd_on_device, t, out=out)   # out.points, out.normals: wp.array

:func:`skin_mesh` and :func:`skin_crowd` have the call shape of :mod:`vbusd.decoders.reference`'s functions
of the same names (plus ``device=``) and return numpy arrays; ``vbusd decode --device`` uses them.

Texel upload (exact path): the texture is uploaded once as float32 channel values, dequantized on
the host in float64 for unorm16 (exactly the reference's values, rounded once to float32).
float16 -> float32 is exact, so this loses nothing for float16 and float32 textures, and one kernel
serves every texel format; the bone decode reads only instances x bones x 2T texels per call, so
the doubled texel size costs no measurable time. The hardware path (``sampling="hardware"``)
instead uploads the texels in their stored format into a ``wp.Texture2D`` and lets the texture unit
filter between rows, as a vertex shader would; spec/hardware-sampling.md measures the difference.

Kernels and their numpy twins: :mod:`vbusd.decoders.warp_kernels`.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from typing import Optional, Union

import numpy as np

import warp as wp

from vbusd.decoders import warp_kernels as K
from vbusd.format.errors import InputError, OptionsError
from vbusd.format.layout import Encoding, TexelFormat
from vbusd.format.model import BoundMesh, Crowd, VirtualBones
from vbusd.decoders.reference import blends_as_layers, channel_values, normal_point_indices
from vbusd.decoders.reference import DEFAULT_FRAME_INTERVAL, check_frame_interval, check_root_motion_scales
from vbusd.kernels.warp_setup import _WARP_INIT_NOTES, _init_warp, quiet_warp  # noqa: F401  (quiet_warp: public here)
from vbusd.format.errors import UnsupportedError

__all__ = ["quiet_warp", "SAMPLING_MODES", "available_devices", "SkinResult", "DeviceCrowd",
           "BoneBuffers", "Decoder", "skin_mesh", "skin_mesh_crossfade", "skin_crowd", "skin_crowd_previous",
           "root_motion_crowd"]



def _quietly(function):
    """Decorator: run a public warp entry point inside :func:`quiet_warp`."""
    @functools.wraps(function)
    def wrapper(*args, **kwargs):
        with quiet_warp():
            return function(*args, **kwargs)
    return wrapper


SAMPLING_MODES = ("exact", "hardware")
"""``exact``: the spec's blend in float32 arithmetic; ``hardware``: the texture unit's filter."""


def available_devices() -> list:
    """Warp device names usable here: ``"cpu"`` (when warp's CPU backend loads) and ``"cuda"``."""
    _init_warp()
    devices = []
    if wp.is_cpu_available():
        devices.append("cpu")
    if wp.is_cuda_available():
        devices.append("cuda")
    return devices


def _resolve_device(device) -> "wp.context.Device":
    if device is None:
        raise OptionsError("a device must be given explicitly (\"cpu\" or \"cuda\")", file="decode")
    name = str(device)
    _init_warp()
    if name.startswith("cuda") and not wp.is_cuda_available():
        # In vbusd's words, not warp's: its native note names library internals.
        notes = " ".join(_WARP_INIT_NOTES).lower()
        why = " (no NVIDIA CUDA driver was found)" if "driver" in notes else ""
        instead = "use --device cpu, or leave --device out for the numpy reference decoder" \
            if "cpu" in available_devices() else "leave --device out for the numpy reference decoder"
        raise OptionsError(f"device {name!r} requested but no CUDA device is available here{why}; {instead}",
                           file="decode")
    if name == "cpu" and not wp.is_cpu_available():
        raise OptionsError("device 'cpu' requested but warp's CPU backend is not available",
                           file="decode")
    try:
        return wp.get_device(name)
    except Exception as error:  # warp raises RuntimeError/ValueError for unknown names
        raise OptionsError(f"unknown device {name!r}: {error}", file="decode") from None


@dataclass
class SkinResult:
    """Skinned output on the device.

    Attributes:
        points: (instances, V) ``wp.vec3`` array of float32 positions.
        normals: (instances, V') ``wp.vec3`` array of unit normals, or None when the mesh has none.
    """

    points: wp.array
    normals: Optional[wp.array]

    @property
    def instance_count(self) -> int:
        """Number of instances (or times) the arrays hold."""
        return int(self.points.shape[0])

    def numpy(self) -> tuple:
        """(points (n, V, 3), normals (n, V', 3) or None) as float32 numpy arrays (copies to host)."""
        points = self.points.numpy()
        normals = None if self.normals is None else self.normals.numpy()
        return points, normals


@dataclass
class DeviceCrowd:
    """A crowd's per-instance arrays, uploaded once (see :meth:`Decoder.upload_crowd`)."""

    clip: wp.array
    time_offset: wp.array
    playback_rate: wp.array
    positions: wp.array
    orientations: wp.array
    scales: wp.array
    uniform_scale: bool = True
    fade_clip: Optional[wp.array] = None
    fade_time_offset: Optional[wp.array] = None
    fade_playback_rate: Optional[wp.array] = None
    fade_weight: Optional[wp.array] = None
    fades: bool = False
    layer_clip: Optional[wp.array] = None
    """Format 1.2 layers (spec "Layers and bone masks"): (n, L) arrays, None without layers."""
    layer_time_offset: Optional[wp.array] = None
    layer_playback_rate: Optional[wp.array] = None
    layer_weight: Optional[wp.array] = None
    layer_mask: Optional[wp.array] = None
    layer_mode: Optional[wp.array] = None
    """Format 1.3 (spec 23.4): (n, L) 0 override, 1 additive; with the reference clip and time of each layer."""
    layer_reference_clip: Optional[wp.array] = None
    layer_reference_time: Optional[wp.array] = None

    @property
    def instance_count(self) -> int:
        """Number of instances."""
        return int(self.clip.shape[0])

    @property
    def layer_count(self) -> int:
        """L: layers per instance (0 without layers)."""
        return 0 if self.layer_weight is None else int(self.layer_weight.shape[1])


@dataclass
class BoneBuffers:
    """Decoded bones of every instance: the intermediate the skinning kernel reads.

    Structure of arrays, float32: ``linear`` (n, 12, B) the placed ``[A | t]`` row by row (LBS
    encodings), ``normal`` (n, 9, B) placed normal matrices (affineMatrix, quatTranslation, or
    non-uniformly scaled instances), ``dual`` (n, 8, B) dual quaternions (dualQuat) and
    ``dual_fade`` (n, 8, B) those of the fade clip of crossfading instances. A skinning
    warp gathers one component of its vertices' bones per load: with bones innermost, those
    addresses fall in one or two cache lines instead of one 48-byte matrix each. Unused buffers are
    1x1x1 placeholders. ``frames`` (n,) holds the per-instance rows, blend and placement.
    """

    linear: wp.array
    normal: wp.array
    dual: wp.array
    frames: wp.array
    dual_fade: Optional[wp.array] = None


class Decoder:
    """Keeps one Virtual Bones texture and one bound mesh on a device and skins them on demand.

    Args:
        vb: The baked animation.
        mesh: The mesh to skin; defaults to ``vb.meshes[0]``.
        device: ``"cpu"``, ``"cuda"`` or ``"cuda:N"``; required (no implicit default device).
        sampling: ``"exact"`` (default; the spec's interpolation) or ``"hardware"`` (rows blended by
            the texture unit through ``wp.Texture2D``; see spec/hardware-sampling.md).
        instances_per_thread: Instances a skinning thread handles for its vertex (its rest data is
            loaded once for all of them). None: as many (up to 16) as leave at least a million
            threads on CUDA; 1 on the CPU.
        block_dim: Threads per CUDA block of the skinning launch. None: 128 (fastest measured on an
            H200 and on an H100, ahead of 256 and 512).

    Each vertex's weights must sum to one, as the format requires: the instancer transform is
    folded into the decoded bones (``warp_kernels.place_bone``), which equals applying it after
    skinning only then.

    Raises:
        OptionsError: Unknown device or sampling mode, no mesh.
        InputError: Mesh bone indices outside the texture's bones, mismatched mesh arrays,
            faceVarying indices outside the points.
    """

    @_quietly
    def __init__(self, vb: VirtualBones, mesh: Optional[BoundMesh] = None, *, device,
                 sampling: str = "exact", instances_per_thread: Optional[int] = None,
                 block_dim: Optional[int] = None) -> None:
        if sampling not in SAMPLING_MODES:
            raise OptionsError(f"sampling must be one of {', '.join(SAMPLING_MODES)}, got {sampling!r}",
                               file="decode")
        if mesh is None:
            if not vb.meshes:
                raise OptionsError("the animation has no bound mesh to skin", file="decode",
                                   location=vb.path)
            mesh = vb.meshes[0]
        self.device = _resolve_device(device)
        self.vb = vb
        self.mesh = mesh
        self.sampling = sampling
        self.encoding = vb.layout.encoding
        if self.encoding is Encoding.COMPACT_QUAT_TRANSLATION and sampling != "exact":
            raise OptionsError("compactQuatTranslation texels are integers, read with texelFetch only "
                               "(spec 9.4): use sampling='exact'", file="decode")
        self.encoding_id = K.ENCODING_IDS[self.encoding.value]
        self.bone_count = vb.layout.bone_count
        self.vertex_count = int(np.asarray(mesh.points).shape[0])
        if instances_per_thread is not None and (isinstance(instances_per_thread, bool) or
                                                 int(instances_per_thread) != instances_per_thread or
                                                 instances_per_thread < 1):
            raise OptionsError(f"instances_per_thread must be a positive integer, got {instances_per_thread!r}",
                               file="decode")
        self.instances_per_thread = instances_per_thread
        if block_dim is not None and (isinstance(block_dim, bool) or int(block_dim) != block_dim or
                                      not 1 <= block_dim <= 1024):
            raise OptionsError(f"block_dim must be an integer in 1..1024, got {block_dim!r}", file="decode")
        self.block_dim = 128 if block_dim is None else int(block_dim)
        self._check_mesh(mesh)
        self._upload_texture()
        self._upload_clips()
        self._upload_mesh(mesh)
        self._bones: dict = {}
        self._crowd_cache: tuple = (None, None)

    # ---------------------------------------------------------------------------------- uploads

    def _array(self, data, dtype) -> wp.array:
        return wp.array(data, dtype=dtype, device=self.device)

    def _check_mesh(self, mesh: BoundMesh) -> None:
        points = np.asarray(mesh.points)
        idx = np.asarray(mesh.bone_indices)
        w = np.asarray(mesh.bone_weights)
        if points.ndim != 2 or points.shape[1] != 3:
            raise InputError(f"points must be (V, 3), got {points.shape}", location=mesh.path, code="binding.mesh")
        if idx.ndim != 2 or idx.shape != w.shape or idx.shape[0] != points.shape[0] or idx.shape[1] < 1:
            raise InputError(f"bone indices {idx.shape} and weights {w.shape} must be (V, K) for "
                             f"{points.shape[0]} points", location=mesh.path, code="binding.count")
        if idx.size and (idx.min() < 0 or idx.max() >= self.bone_count):
            bad = int(idx.max() if idx.max() >= self.bone_count else idx.min())
            raise InputError(f"bone index {bad} out of range 0..{self.bone_count - 1}", location=mesh.path,
                             code="binding.indices.range")
        if mesh.normals is not None:
            expected = points.shape[0] if mesh.normals_interpolation != "faceVarying" else \
                np.asarray(mesh.face_vertex_indices).shape[0]
            if np.asarray(mesh.normals).shape != (expected, 3):
                raise InputError(f"{mesh.normals_interpolation} normals must be ({expected}, 3), got "
                                 f"{np.asarray(mesh.normals).shape}", location=mesh.path, code="binding.normals.count")
            corners = np.asarray(mesh.face_vertex_indices)
            if mesh.normals_interpolation == "faceVarying" and corners.size and \
                    (corners.min() < 0 or corners.max() >= points.shape[0]):
                raise InputError(f"faceVertexIndices reach {int(corners.max())}, outside the {points.shape[0]} "
                                 f"points", location=mesh.path, code="binding.mesh")

    def _upload_texture(self) -> None:
        vb, layout = self.vb, self.vb.layout
        self.unorm = layout.texel_format is TexelFormat.UNORM16
        if self.sampling == "exact":
            values = channel_values(vb)  # (rows, B, T, 4) float64, dequantized like the reference
            # compactQuatTranslation: its words unpacked into 2 vec4 per bone (quaternion; t and 1)
            columns = values.shape[1] * values.shape[2]
            texels = np.zeros((layout.height, max(layout.width, columns), 4), dtype=np.float32)
            texels[:layout.row_count, :columns] = values.reshape(layout.row_count, columns, 4)
            self.texels = self._array(texels, wp.vec4)
            self.texture = None
            return
        self.texels = None
        self.texture = wp.Texture2D(np.ascontiguousarray(vb.texels), filter_mode=wp.TextureFilterMode.LINEAR,
                                    address_mode=wp.TextureAddressMode.CLAMP, normalized_coords=False,
                                    device=self.device)
        if self.unorm:
            ranges = np.asarray(vb.unorm_ranges, dtype=np.float64)  # (T, 4, 2)
            low, span = ranges[..., 0], ranges[..., 1] - ranges[..., 0]
        else:
            low = span = np.zeros((layout.texels_per_bone, 4))
        self.unorm_low = self._array(low.astype(np.float32), wp.vec4)
        self.unorm_span = self._array(span.astype(np.float32), wp.vec4)

    def _upload_clips(self) -> None:
        clips = self.vb.clips
        self.clip_count = len(clips)
        self.clip_first_row = self._array(np.array([c.first_row for c in clips], np.int32), wp.int32)
        self.clip_row_count = self._array(np.array([c.row_count for c in clips], np.int32), wp.int32)
        self.clip_rate = self._array(np.array([c.rows_per_second for c in clips], np.float64), wp.float64)
        self.clip_loop = self._array(np.array([1 if c.loop else 0 for c in clips], np.int32), wp.int32)

    def _upload_mesh(self, mesh: BoundMesh) -> None:
        self.points = self._array(np.asarray(mesh.points, np.float32), wp.vec3)
        self.indices = self._array(np.ascontiguousarray(mesh.bone_indices, np.int32), wp.int32)
        self.weights = self._array(np.ascontiguousarray(mesh.bone_weights, np.float32), wp.float32)
        self.with_normals = mesh.normals is not None
        self.face_varying = normal_point_indices(mesh) is not None
        if self.with_normals:
            self.normals = self._array(np.asarray(mesh.normals, np.float32), wp.vec3)
            self.normal_count = int(self.normals.shape[0])
        else:
            self.normals = self._array(np.zeros((1, 3), np.float32), wp.vec3)
            self.normal_count = 0
        if self.face_varying:
            self.normal_points = self._array(normal_point_indices(mesh).astype(np.int32), wp.int32)

    @_quietly
    def upload_crowd(self, crowd: Crowd) -> DeviceCrowd:
        """Upload a crowd's per-instance arrays once; pass the result to :meth:`skin_crowd`.

        Orientations are normalized on the host in float64 (as the reference does); clip offsets
        and rates are widened to float64 so instance times match the reference exactly.

        Raises:
            InputError: A clip index out of range or mismatched per-instance array lengths.
        """
        n = crowd.instance_count
        if crowd.blended:
            # Blend spaces (spec 23.7) decode as layers under a mask of every bone (23.1).
            crowd = blends_as_layers(self.vb, crowd)
        layers = self._layer_arrays(crowd) if crowd.layered else {}
        clip = np.asarray(crowd.clip, dtype=np.int64).reshape(-1)
        arrays = {"clip": clip, "timeOffset": np.asarray(crowd.time_offset).reshape(-1),
                  "playbackRate": np.asarray(crowd.playback_rate).reshape(-1)}
        for name, value in arrays.items():
            if value.shape[0] != n:
                raise InputError(f"primvars:vb:{name} has {value.shape[0]} values for {n} instances",
                                 location=crowd.path, code="instancer.count")
        if n and (clip.min() < 0 or clip.max() >= self.clip_count):
            bad = int(clip.max() if clip.max() >= self.clip_count else clip.min())
            raise InputError(f"clip index {bad} out of range 0..{self.clip_count - 1}",
                             location=f"{crowd.path}.primvars:vb:clip", code="instancer.clip.range")
        q = np.asarray(crowd.orientations, dtype=np.float64).reshape(n, 4)
        length = np.linalg.norm(q, axis=1, keepdims=True)
        q = q / np.where(length > 0, length, 1.0)
        scales = np.ones((n, 3)) if crowd.scales is None else np.asarray(crowd.scales, np.float64).reshape(n, 3)
        fade_clip, fade_offset, fade_rate, fade_weight = crowd.fade_arrays()
        if crowd.crossfades and (fade_clip.min() < 0 or fade_clip.max() >= self.clip_count):
            bad = int(fade_clip.max() if fade_clip.max() >= self.clip_count else fade_clip.min())
            raise InputError(f"fade clip index {bad} out of range 0..{self.clip_count - 1}",
                             location=f"{crowd.path}.primvars:vb:fadeClip", code="instancer.clip.range")
        return DeviceCrowd(
            clip=self._array(clip.astype(np.int32), wp.int32),
            time_offset=self._array(np.asarray(crowd.time_offset, np.float64).reshape(n), wp.float64),
            playback_rate=self._array(np.asarray(crowd.playback_rate, np.float64).reshape(n), wp.float64),
            positions=self._array(np.asarray(crowd.positions, np.float32).reshape(n, 3), wp.vec3),
            orientations=self._array(q.astype(np.float32), wp.quat),
            scales=self._array(scales.astype(np.float32), wp.vec3),
            uniform_scale=bool(np.all(scales == scales[:, :1])),
            **self._fade_arrays(fade_clip, fade_offset, fade_rate, fade_weight), **layers)

    def _layer_arrays(self, crowd: Crowd) -> dict:
        """The DeviceCrowd fields of a layered crowd (format 1.2), with the animation's rig uploaded once.

        Raises:
            UnsupportedError: Hardware sampling (the layer kernel reads exact texels) (code
                ``layers.unsupported``).
            InputError: The animation stores no masks, a mask or clip index out of range (code
                ``layers.noMask``, ``instancer.clip.range``).
        """

        vb = self.vb
        where = f"{crowd.path}.primvars:vb:layerWeight"
        if self.sampling != "exact":
            raise UnsupportedError("layers (format 1.2) are decoded on the exact path only; use sampling='exact'",
                                   location=where, code="layers.unsupported")
        if (not vb.masks and not vb.blend_spaces) or vb.bone_parents is None or vb.bind_transforms is None:
            raise InputError("the crowd plays layers but its animation stores no bone masks (format 1.2)",
                             location=where, code="layers.noMask")
        weight = np.asarray(crowd.layer_weight, np.float32)
        n, count = weight.shape
        clip = np.asarray(crowd.layer_clip, np.int64).reshape(n, count)
        mask = np.asarray(crowd.layer_mask, np.int64).reshape(n, count)
        active = weight > 0
        if np.any(active & ((clip < 0) | (clip >= self.clip_count))):
            raise InputError(f"a layer clip index is outside 0..{self.clip_count - 1}", location=where,
                             code="instancer.clip.range")
        # Mask index len(vb.masks) is the mask of every bone that blend spaces decode with (spec 23.1).
        masks_there = len(vb.masks) + (1 if vb.blend_spaces else 0)
        if np.any(active & ((mask < 0) | (mask >= masks_there))):
            raise InputError(f"a layer mask index is outside 0..{len(vb.masks) - 1}", location=where,
                             code="layers.noMask")
        if not hasattr(self, "rig_bind"):
            binds = np.asarray(vb.bind_transforms, np.float64)
            self.rig_bind = self._array(binds.astype(np.float32), wp.mat44)
            self.rig_inverse_bind = self._array(np.linalg.inv(binds).astype(np.float32), wp.mat44)
            self.rig_parents = self._array(np.asarray(vb.bone_parents, np.int32), wp.int32)
            rows = [np.asarray(w, np.float32) for _, w in vb.masks] + [np.ones(vb.layout.bone_count, np.float32)]
            self.rig_masks = self._array(np.stack(rows), wp.float32)
        return dict(layer_clip=self._array(np.where(active, clip, 0).astype(np.int32), wp.int32),
                    layer_time_offset=self._array(np.asarray(crowd.layer_time_offset, np.float64).reshape(n, count),
                                                  wp.float64),
                    layer_playback_rate=self._array(np.asarray(crowd.layer_playback_rate, np.float64).reshape(n, count),
                                                    wp.float64),
                    layer_weight=self._array(np.clip(weight, 0.0, 1.0), wp.float32),
                    layer_mask=self._array(np.where(active, mask, 0).astype(np.int32), wp.int32),
                    **self._additive_arrays(crowd, clip, active))

    def _additive_arrays(self, crowd: Crowd, clip: np.ndarray, active: np.ndarray) -> dict:
        """The DeviceCrowd fields of additive layers (format 1.3, spec 23.4): modes, reference clips and times."""
        shape = clip.shape
        mode = np.zeros(shape, np.int32) if crowd.layer_mode is None else np.asarray(crowd.layer_mode).reshape(shape)
        reference = clip if crowd.layer_reference_clip is None else np.asarray(crowd.layer_reference_clip).reshape(shape)
        time = (np.zeros(shape) if crowd.layer_reference_time is None
                else np.asarray(crowd.layer_reference_time, np.float64).reshape(shape))
        additive = active & (mode == 1)
        if np.any(additive & ((reference < 0) | (reference >= self.clip_count))):
            raise InputError(f"a layer reference clip index is outside 0..{self.clip_count - 1}",
                             location=f"{crowd.path}.primvars:vb:layerReferenceClip", code="instancer.clip.range")
        return dict(layer_mode=self._array(np.where(additive, 1, 0).astype(np.int32), wp.int32),
                    layer_reference_clip=self._array(np.where(additive, reference, 0).astype(np.int32), wp.int32),
                    layer_reference_time=self._array(time, wp.float64))

    def _fade_arrays(self, fade_clip, fade_offset, fade_rate, fade_weight) -> dict:
        """The DeviceCrowd fields of a crossfade (spec "Crossfade"): clip, offset, rate, weight per instance."""
        weight = np.clip(np.asarray(fade_weight, np.float64), 0.0, 1.0)
        return dict(fade_clip=self._array(np.asarray(fade_clip).astype(np.int32), wp.int32),
                    fade_time_offset=self._array(np.asarray(fade_offset, np.float64), wp.float64),
                    fade_playback_rate=self._array(np.asarray(fade_rate, np.float64), wp.float64),
                    fade_weight=self._array(weight.astype(np.float32), wp.float32),
                    fades=bool(np.any(weight > 0)))

    def _check_clip(self, clip_index) -> int:
        if isinstance(clip_index, bool) or int(clip_index) != clip_index or not 0 <= clip_index < self.clip_count:
            raise OptionsError(f"clip index {clip_index!r} out of range 0..{self.clip_count - 1}",
                               file="decode")
        return int(clip_index)

    @staticmethod
    def _finite_times(tau) -> np.ndarray:
        tau = np.atleast_1d(np.asarray(tau, dtype=np.float64)).reshape(-1)
        if not np.all(np.isfinite(tau)):
            raise OptionsError("times must be finite", file="decode")
        return tau

    def _times_crowd(self, clip_index: int, tau, fade=None) -> DeviceCrowd:
        """A crowd of untransformed instances at clip-local times ``tau`` (for :meth:`skin`).

        ``fade``: None, or (fade clip, fade clip-local times, fade weights) for a crossfade.
        """
        clip_index = self._check_clip(clip_index)
        tau = self._finite_times(tau)
        n = tau.shape[0]
        identity = np.zeros((n, 4), np.float32)
        identity[:, 3] = 1.0
        if fade is None:
            fade_arrays = (np.zeros(n), np.zeros(n), np.ones(n), np.zeros(n))
        else:
            fade_clip, fade_tau, fade_weight = fade
            fade_tau = np.broadcast_to(self._finite_times(fade_tau), (n,))
            weight = np.broadcast_to(np.asarray(fade_weight, np.float64).reshape(-1), (n,))
            if not np.all(np.isfinite(weight)):
                raise OptionsError("fade weights must be finite", file="decode")
            fade_arrays = (np.full(n, self._check_clip(fade_clip)), fade_tau, np.zeros(n), weight)
        return DeviceCrowd(
            clip=self._array(np.full(n, int(clip_index), np.int32), wp.int32),
            time_offset=self._array(tau, wp.float64),
            playback_rate=self._array(np.zeros(n), wp.float64),
            positions=self._array(np.zeros((n, 3), np.float32), wp.vec3),
            orientations=self._array(identity, wp.quat),
            scales=self._array(np.ones((n, 3), np.float32), wp.vec3),
            **self._fade_arrays(*fade_arrays))

    # ---------------------------------------------------------------------------------- buffers

    @_quietly
    def allocate(self, instance_count: int) -> SkinResult:
        """Output arrays for ``instance_count`` instances, to reuse through ``out=`` every frame."""
        points = wp.empty((instance_count, self.vertex_count), dtype=wp.vec3, device=self.device)
        normals = None
        if self.with_normals:
            normals = wp.empty((instance_count, self.normal_count), dtype=wp.vec3, device=self.device)
        return SkinResult(points, normals)

    def _separate_normals(self, crowd: DeviceCrowd) -> bool:
        """Whether placed bones need their own normal matrices (else N is the linear part of M)."""
        if self.encoding in (Encoding.AFFINE_MATRIX, Encoding.QUAT_TRANSLATION):
            return True
        if crowd.layer_count and self.encoding is Encoding.CROSS_MATRIX:
            return True  # a layered bone's normal matrix is inverse(A')^T (spec 8.6), not A itself
        # crossMatrix and compactQuatTranslation: N = A (a rotation) until a non-uniform scale places it
        return self.encoding in (Encoding.CROSS_MATRIX, Encoding.COMPACT_QUAT_TRANSLATION) and not crowd.uniform_scale

    def _bone_buffers(self, n: int, own_normal: bool, fades: bool = False) -> BoneBuffers:
        fade_dual = fades and self.encoding is Encoding.DUAL_QUAT
        buffers = self._bones.get((n, own_normal, fade_dual))
        if buffers is None:
            b = self.bone_count
            placeholder = (1, 1, 1)
            lbs = self.encoding is not Encoding.DUAL_QUAT
            buffers = BoneBuffers(
                linear=wp.empty((n, 12, b) if lbs else placeholder, dtype=float, device=self.device),
                normal=wp.empty((n, 9, b) if own_normal else placeholder, dtype=float, device=self.device),
                dual=wp.empty(placeholder if lbs else (n, 8, b), dtype=float, device=self.device),
                frames=wp.empty(n, dtype=K.InstanceFrame, device=self.device),
                dual_fade=wp.empty((n, 8, b) if fade_dual else placeholder, dtype=float, device=self.device))
            self._bones = {(n, own_normal, fade_dual): buffers}  # keep one size: a renderer calls with one crowd
        return buffers

    # ---------------------------------------------------------------------------------- launches

    @_quietly
    def decode_bones(self, crowd: DeviceCrowd, t: float, *, fraction_steps: float = 0.0) -> BoneBuffers:
        """Launch the bone decode for every instance at scene time ``t``; returns the buffers.

        Args:
            crowd: Uploaded instances.
            t: Scene time (s); each instance plays at ``timeOffset + playbackRate * t``.
            fraction_steps: Exact path only: round the row fraction to multiples of
                ``1 / fraction_steps`` (truncate to ``1 / -fraction_steps`` when negative; 0: the spec's
                exact blend). Used to model the texture unit's filter weights.
        """
        n = crowd.instance_count
        separate = self._separate_normals(crowd)
        buffers = self._bone_buffers(n, separate, crowd.fades)
        if n == 0:
            return buffers
        if self.sampling == "hardware" and fraction_steps:
            raise OptionsError("fraction_steps models the texture unit on the exact path only", file="decode")
        frames = buffers.frames
        wp.launch(K.instance_frames_kernel, dim=n, device=self.device,
                  inputs=[self.clip_first_row, self.clip_row_count, self.clip_rate, self.clip_loop, crowd.clip,
                          crowd.time_offset, crowd.playback_rate, wp.float64(t), float(fraction_steps),
                          crowd.positions, crowd.orientations, crowd.scales, crowd.fade_clip,
                          crowd.fade_time_offset, crowd.fade_playback_rate, crowd.fade_weight, frames])
        outputs = [buffers.linear, buffers.normal, buffers.dual, buffers.dual_fade]
        dim = (n, self.bone_count)
        if self.sampling == "exact":
            wp.launch(K.decode_bones, dim=dim, device=self.device,
                      inputs=[self.texels, self.encoding_id, frames, int(separate), *outputs])
            if crowd.layer_count:
                # Layers (spec 8.6): each layer's rows, then the bones they change rewritten.
                rows = wp.empty((n, crowd.layer_count, 3), dtype=float, device=self.device)
                wp.launch(K.layer_rows_kernel, dim=(n, crowd.layer_count), device=self.device,
                          inputs=[self.clip_first_row, self.clip_row_count, self.clip_rate, self.clip_loop,
                                  crowd.layer_clip, crowd.layer_time_offset, crowd.layer_playback_rate,
                                  wp.float64(t), rows])
                # Additive layers' reference poses (spec 23.4): their clips at their fixed times.
                reference_rows = wp.empty((n, crowd.layer_count, 3), dtype=float, device=self.device)
                wp.launch(K.layer_rows_kernel, dim=(n, crowd.layer_count), device=self.device,
                          inputs=[self.clip_first_row, self.clip_row_count, self.clip_rate, self.clip_loop,
                                  crowd.layer_reference_clip, crowd.layer_reference_time,
                                  wp.zeros((n, crowd.layer_count), dtype=wp.float64, device=self.device),
                                  wp.float64(t), reference_rows])
                wp.launch(K.layer_bones, dim=dim, device=self.device,
                          inputs=[self.texels, self.encoding_id, frames, int(separate), rows, crowd.layer_count,
                                  crowd.layer_weight, crowd.layer_mask, self.rig_bind, self.rig_inverse_bind,
                                  self.rig_parents, self.rig_masks, crowd.layer_mode, reference_rows, *outputs])
        else:
            wp.launch(K.decode_bones_texture, dim=dim, device=self.device,
                      inputs=[self.texture, self.encoding_id, int(self.unorm), self.unorm_low, self.unorm_span,
                              frames, int(separate), *outputs])
        return buffers

    @_quietly
    def skin_bones(self, crowd: DeviceCrowd, buffers: BoneBuffers, out: SkinResult) -> SkinResult:
        """Launch the skinning of every (instance, vertex) from decoded bone buffers into ``out``."""
        n = crowd.instance_count
        if n == 0:
            return out
        fused_normals = int(self.with_normals and not self.face_varying)
        separate = int(self._separate_normals(crowd))
        ipt = self._instances_per_thread(n)
        dim = ((n + ipt - 1) // ipt, self.vertex_count)
        out_normals = out.normals if fused_normals else out.points  # placeholder when unused
        mesh = [self.points, self.normals, fused_normals, self.indices, self.weights]
        if self.encoding is Encoding.DUAL_QUAT:
            wp.launch(K.skin_dqs_kernel, dim=dim, device=self.device, block_dim=self.block_dim,
                      inputs=[buffers.dual, buffers.dual_fade, buffers.frames, *mesh, crowd.positions, crowd.orientations, crowd.scales, ipt,
                              out.points, out_normals])
        else:
            wp.launch(K.skin_lbs_kernel(int(self.indices.shape[1])), dim=dim, device=self.device,
                      block_dim=self.block_dim,
                      inputs=[buffers.linear, buffers.normal, separate, *mesh, ipt, out.points, out_normals])
        if self.with_normals and self.face_varying:
            wp.launch(K.skin_normals_kernel, dim=(n, self.normal_count), device=self.device,
                      inputs=[self.encoding_id, buffers.linear, buffers.normal, separate, buffers.dual,
                              buffers.dual_fade, buffers.frames, self.normals,
                              self.normal_points, self.indices, self.weights, crowd.orientations, crowd.scales,
                              out.normals])
        return out

    def _instances_per_thread(self, n: int) -> int:
        if self.instances_per_thread is not None:
            return self.instances_per_thread
        if not self.device.is_cuda:
            return 1
        # Measured on an H200 and an H100 (benchmarks/README.md): 16 instances per thread was
        # fastest on the large crowds; small crowds need every thread they can get to fill the GPU.
        ipt = 16
        while ipt > 1 and -(-n // ipt) * self.vertex_count < 1_000_000:
            ipt //= 2
        return ipt

    def _check_out(self, out: Optional[SkinResult], n: int) -> SkinResult:
        if out is None:
            return self.allocate(n)
        if out.points.shape != (n, self.vertex_count) or out.points.device != self.device or \
                (self.with_normals and (out.normals is None or out.normals.shape != (n, self.normal_count))):
            raise OptionsError(f"out arrays do not fit {n} instances of this mesh on {self.device}; "
                               f"use Decoder.allocate({n})", file="decode")
        return out

    @_quietly
    def skin_crowd(self, crowd: Union[Crowd, DeviceCrowd], t: float, out: Optional[SkinResult] = None,
                   *, fraction_steps: float = 0.0) -> SkinResult:
        """World-space points and normals of every instance at scene time ``t`` (three launches).

        Twin of ``reference.skin_crowd``. A :class:`~vbusd.format.model.Crowd` is uploaded on its first
        call and reused while the same object is passed again; pass a :class:`DeviceCrowd` from
        :meth:`upload_crowd` to manage that yourself.

        Args:
            crowd: The instances.
            t: Scene time in seconds.
            out: Arrays from :meth:`allocate` to write into (no allocation per call), or None.
            fraction_steps: See :meth:`decode_bones`.

        Returns:
            ``out`` (or new arrays): points (N, V) and normals (N, V') as ``wp.vec3`` arrays.
        """
        if not np.isfinite(t):
            raise OptionsError(f"scene time must be finite, got {t!r}", file="decode")
        if isinstance(crowd, Crowd) and crowd.fade_samples:
            crowd = self.upload_crowd(crowd.at(t))  # time-sampled fades: this time's values
        elif isinstance(crowd, Crowd):
            if self._crowd_cache[0] is not crowd:
                self._crowd_cache = (crowd, self.upload_crowd(crowd))
            crowd = self._crowd_cache[1]
        out = self._check_out(out, crowd.instance_count)
        buffers = self.decode_bones(crowd, t, fraction_steps=fraction_steps)
        return self.skin_bones(crowd, buffers, out)

    @_quietly
    def skin_crowd_previous(self, crowd: Union[Crowd, DeviceCrowd], t: float, dt: float = DEFAULT_FRAME_INTERVAL,
                            out: Optional[SkinResult] = None, *, reset=None, previous_crowd: Optional[Crowd] = None,
                            current: Optional[SkinResult] = None) -> SkinResult:
        """Every instance's previous-frame pose (spec 21), twin of ``reference.skin_crowd_previous``.

        The crowd at scene time ``t - dt`` by :meth:`skin_crowd`'s own rules (per-instance clip times,
        crossfade and layers at ``t - dt``), placed by ``previous_crowd``'s transforms when given;
        a reset instance gets its current pose (``hold_reset_kernel``).

        Args:
            crowd: The instances (a :class:`DeviceCrowd` only without ``previous_crowd``).
            t: Scene time (s) of the current frame.
            dt: Frame interval (s), finite and above 0.
            out: Arrays from :meth:`allocate` for the previous pose, or None.
            reset: None, or one flag per instance (clip switched or teleported this frame).
            previous_crowd: The instances' previous transforms (positions, orientations, scales).
            current: This frame's :meth:`skin_crowd` result, when the caller has it (read for reset
                instances instead of skinning the current frame again).

        Returns:
            ``out`` (or new arrays) with the previous points and normals on the device.
        """
        dt = check_frame_interval(dt, "decode")
        if not np.isfinite(t):
            raise OptionsError(f"scene time must be finite, got {t!r}", file="decode")
        placed = crowd
        if previous_crowd is not None:
            if not isinstance(crowd, Crowd):
                raise OptionsError("previous_crowd needs the crowd as a Crowd, not a DeviceCrowd", file="decode")
            if previous_crowd.instance_count != crowd.instance_count:
                raise OptionsError(f"previous_crowd has {previous_crowd.instance_count} instances, the crowd "
                                   f"{crowd.instance_count}", file="decode")
            placed = dataclasses.replace(crowd, positions=previous_crowd.positions,
                                         orientations=previous_crowd.orientations, scales=previous_crowd.scales)
            if not placed.fade_samples:
                placed = self.upload_crowd(placed)  # not cached: the current crowd keeps its upload
        out = self.skin_crowd(placed, t - dt, out)
        flags = None if reset is None else np.asarray(reset, dtype=bool).reshape(-1)
        if flags is not None and flags.shape[0] != out.instance_count:
            raise OptionsError(f"reset has {flags.shape[0]} flags for {out.instance_count} instances", file="decode")
        if flags is not None and flags.any():
            if current is None:
                current = self.skin_crowd(crowd, t)
            reset_array = self._array(flags.astype(np.int32), wp.int32)
            wp.launch(K.hold_reset_kernel, dim=out.points.shape, inputs=[reset_array, current.points, out.points],
                      device=self.device)
            if out.normals is not None:
                wp.launch(K.hold_reset_kernel, dim=out.normals.shape,
                          inputs=[reset_array, current.normals, out.normals], device=self.device)
        return out

    @_quietly
    def skin(self, clip_index: int, tau, out: Optional[SkinResult] = None, *,
             fraction_steps: float = 0.0) -> SkinResult:
        """Skinned points and normals of the mesh at clip-local times ``tau`` (twin of ``reference.skin_mesh``).

        Args:
            clip_index: Index into ``vb.clips``.
            tau: Clip-local times in seconds (scalar or array of n).
            out: Arrays from :meth:`allocate` (n instances), or None.
            fraction_steps: See :meth:`decode_bones`.

        Returns:
            Points (n, V) and normals (n, V') on the device.
        """
        crowd = self._times_crowd(clip_index, tau)
        out = self._check_out(out, crowd.instance_count)
        buffers = self.decode_bones(crowd, 0.0, fraction_steps=fraction_steps)
        return self.skin_bones(crowd, buffers, out)

    @_quietly
    def skin_crossfade(self, clip_index: int, tau, fade_clip: int, fade_tau, fade_weight,
                       out: Optional[SkinResult] = None) -> SkinResult:
        """The mesh crossfading two clips (twin of ``reference.skin_mesh_crossfade``, spec "Crossfade").

        Args:
            clip_index: Index of the first clip.
            tau: Its clip-local times (n).
            fade_clip: Index of the fade clip.
            fade_tau: The fade clip's clip-local times (n, or one for all).
            fade_weight: Weight of the fade clip (n, or one for all), clamped to [0, 1].
            out: Arrays from :meth:`allocate` (n instances), or None.

        Returns:
            Points (n, V) and normals (n, V') on the device.
        """
        crowd = self._times_crowd(clip_index, tau, fade=(fade_clip, fade_tau, fade_weight))
        out = self._check_out(out, crowd.instance_count)
        buffers = self.decode_bones(crowd, 0.0)
        return self.skin_bones(crowd, buffers, out)

    @_quietly
    def bone_transforms(self, clip_index: int, tau, *, fraction_steps: float = 0.0) -> dict:
        """Decoded bone buffers at clip-local times, as numpy (for tests and inspection).

        Returns:
            ``{"linear": (n, B, 3, 4)}`` plus ``"normal": (n, B, 3, 3)`` for affineMatrix and
            quatTranslation, or ``{"dual": (n, B, 2, 4)}`` for dualQuat.
        """
        crowd = self._times_crowd(clip_index, tau)
        buffers = self.decode_bones(crowd, 0.0, fraction_steps=fraction_steps)
        def matrices(array, rows, cols):
            n, _, b = array.shape
            return np.swapaxes(array.numpy(), 1, 2).reshape(n, b, rows, cols)

        if self.encoding is Encoding.DUAL_QUAT:
            return {"dual": matrices(buffers.dual, 2, 4)}
        result = {"linear": matrices(buffers.linear, 3, 4)}
        if self.encoding in (Encoding.AFFINE_MATRIX, Encoding.QUAT_TRANSLATION):
            result["normal"] = matrices(buffers.normal, 3, 3)
        return result


_LAST_DECODER: list = []  # [(vb, mesh, device, sampling, Decoder)]: the module functions' upload cache


def _cached_decoder(vb: VirtualBones, mesh: BoundMesh, device, sampling: str) -> Decoder:
    """The Decoder of the last call when it was for the same objects: a point cache decodes one
    frame after another, and uploading the texture and mesh once is the point of the Decoder."""
    if _LAST_DECODER:
        last_vb, last_mesh, last_device, last_sampling, decoder = _LAST_DECODER[0]
        if last_vb is vb and last_mesh is mesh and last_device == str(device) and last_sampling == sampling:
            return decoder
    decoder = Decoder(vb, mesh, device=device, sampling=sampling)
    _LAST_DECODER[:] = [(vb, mesh, str(device), sampling, decoder)]
    return decoder


@_quietly
def skin_mesh(vb: VirtualBones, mesh: BoundMesh, clip_index: int, tau, *, device,
              sampling: str = "exact") -> tuple:
    """Skinned points (n, V, 3) and normals of a bound mesh at clip-local times, on ``device``.

    Same call shape and meaning as ``vbusd.decoders.reference.skin_mesh``, plus ``device=``; float32 results.
    Consecutive calls for the same ``vb`` and ``mesh`` objects reuse the uploaded data.
    """
    return _cached_decoder(vb, mesh, device, sampling).skin(clip_index, tau).numpy()


@_quietly
def skin_mesh_crossfade(vb: VirtualBones, mesh: BoundMesh, clip_index: int, tau, fade_clip: int, fade_tau,
                        fade_weight, *, device, sampling: str = "exact") -> tuple:
    """A bound mesh crossfading two clips, on ``device`` (``reference.skin_mesh_crossfade`` plus ``device=``).

    Float32 results; consecutive calls for the same ``vb`` and ``mesh`` objects reuse the uploaded data.
    """
    return _cached_decoder(vb, mesh, device, sampling).skin_crossfade(clip_index, tau, fade_clip, fade_tau,
                                                                      fade_weight).numpy()


@_quietly
def skin_crowd(vb: VirtualBones, mesh: BoundMesh, crowd: Crowd, t: float, *, device,
               sampling: str = "exact") -> tuple:
    """World-space points (N, V, 3) and normals of every instance at scene time ``t``, on ``device``.

    Same call shape and meaning as ``vbusd.decoders.reference.skin_crowd``, plus ``device=``; float32 results.
    Consecutive calls for the same ``vb``, ``mesh`` and ``crowd`` objects reuse the uploaded data.
    """
    return _cached_decoder(vb, mesh, device, sampling).skin_crowd(crowd, t).numpy()


@_quietly
def skin_crowd_previous(vb: VirtualBones, mesh: BoundMesh, crowd: Crowd, t: float,
                        dt: float = DEFAULT_FRAME_INTERVAL, *, device, reset=None,
                        previous_crowd: Optional[Crowd] = None, sampling: str = "exact") -> tuple:
    """Every instance's previous-frame pose (spec 21) on ``device``: ``reference.skin_crowd_previous``
    plus ``device=``; float32 results."""
    return _cached_decoder(vb, mesh, device, sampling).skin_crowd_previous(
        crowd, t, dt, reset=reset, previous_crowd=previous_crowd).numpy()


@_quietly
def root_motion_crowd(vb: VirtualBones, crowd: Crowd, t: float, t0: float = 0.0, *, device) -> Crowd:
    """The crowd with every instance moved by its root displacement at scene time ``t`` (spec 8.5, 21.1)
    on ``device``: ``reference.root_motion_crowd`` plus ``device=`` (``root_motion_kernel``, float64)."""
    if not (np.isfinite(t) and np.isfinite(t0)):
        raise OptionsError(f"scene times must be finite, got t={t!r}, t0={t0!r}", file="root_motion_crowd")
    if vb.root_motion is None or crowd.instance_count == 0:
        return crowd
    device = _resolve_device(device)
    n = crowd.instance_count
    tracks = [np.asarray(track, dtype=np.float64).reshape(-1, 4) for track in vb.root_motion.tracks]
    starts = np.cumsum([0] + [len(track) for track in tracks[:-1]]).astype(np.int32)
    scales = np.ones((n, 3)) if crowd.scales is None else np.asarray(crowd.scales, dtype=np.float64)

    def array(data, dtype):
        return wp.array(np.ascontiguousarray(data), dtype=dtype, device=device)

    positions = wp.zeros(n, dtype=wp.vec3d, device=device)
    orientations = wp.zeros(n, dtype=wp.vec4d, device=device)
    yaw = wp.zeros(n, dtype=wp.float64, device=device)
    wp.launch(K.root_motion_kernel, dim=n, device=device, inputs=[
        array(np.concatenate(tracks), wp.vec4d), array(starts, wp.int32),
        array([c.row_count for c in vb.clips], wp.int32), array([c.rows_per_second for c in vb.clips], wp.float64),
        array([1 if c.loop else 0 for c in vb.clips], wp.int32), 1 if vb.root_motion.up_axis == "Y" else 2,
        array(np.asarray(crowd.clip, np.int32), wp.int32), array(np.asarray(crowd.time_offset, np.float64), wp.float64),
        array(np.asarray(crowd.playback_rate, np.float64), wp.float64), float(t0), float(t),
        array(np.asarray(crowd.positions, np.float64), wp.vec3d),
        array(np.asarray(crowd.orientations, np.float64), wp.vec4d), array(scales, wp.vec3d),
        positions, orientations, yaw])
    check_root_motion_scales(vb.root_motion.up_axis, scales, yaw.numpy())
    return dataclasses.replace(crowd, positions=positions.numpy(), orientations=orientations.numpy())

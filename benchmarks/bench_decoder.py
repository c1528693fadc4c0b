"""Decoder throughput: vertex-instances per second on the CPU (warp vs numpy) and the GPU (warp).

Crowds (the stadium sample's 18-bone crossMatrix float16 texture, 64x512):

* ``talk``: the talk's crowd, 1,200 instances x 202 vertices (the stadium sample itself);
* ``crowd100k``: 100,000 instances x 202 vertices (seeded random placements, offsets and rates);
* ``mesh50k``: 1,000 instances x 50,000 vertices (the 202-vertex body tiled 248 times, shifted).

Per case and device the script times full calls of ``Decoder.skin_crowd`` into preallocated
outputs (per-instance frame, bone decode and skinning launches). On CUDA it also times the decode
(frame + bone decode) and the skinning launch alone, store-only kernels of the same launch
geometry (the store ceiling), a naive single-kernel decoder (one thread per vertex-instance
fetching and decoding its K bones, the DESIGN.md baseline), the hardware texture path, and a
device-to-device copy (``wp.copy`` of a 1 GiB array) in the same run. CUDA times come from CUDA events over repeated calls;
CPU times from ``time.perf_counter`` around synchronized calls.

Bandwidth counting (bytes moved per call, DRAM level, each byte once):

* outputs: positions + normals, float32: 24 bytes per vertex-instance;
* bone buffer: written by the decode launch and read by the skinning launch: 2 x instances x bones x
  48 bytes (crossMatrix ``[A | t]``);
* per-instance inputs: clip, offset, rate (20 bytes) and position, orientation, scale (40 bytes),
  read by the per-instance frame launch, and its frame (rows, blend, placement) written and read once;
* mesh: points, normals, K indices and K weights per vertex (24 + 8K bytes), read once;
* texture: the float32 texel array once (512 KiB for the stadium texture).

The copy rate counts read + write bytes (2 x array size per copy), so the fraction compares like
with like. ``fraction_outputs`` counts only the 24 output bytes (as DESIGN.md's baseline did).

Agreement: on CUDA the talk's crowd (all 1,200 instances) and the first instances of the large
crowds are compared with the numpy reference (max position error / bounding-box diagonal).

Usage::

    python benchmarks/bench_decoder.py                      # every available device
    python benchmarks/bench_decoder.py --devices cpu --json benchmarks/results/decoder_cpu.json
    python benchmarks/bench_decoder.py --devices cuda --json $OUT/decoder_cuda.json   # GPU machine
    python benchmarks/bench_decoder.py --hardware --devices cuda --json $OUT/hardware.json   # hardware path

benchmarks/gpu_run.sh runs the two GPU commands (and the CUDA tests) on the device tool's machine.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import warp as wp  # noqa: E402

from vbusd.decoders import reference  # noqa: E402
from vbusd.decoders import warp as wd  # noqa: E402
from vbusd.decoders import warp_kernels as K  # noqa: E402
from vbusd.io.files import atomic_write  # noqa: E402
from vbusd.format.model import BoundMesh, Crowd  # noqa: E402

COPY_BYTES = 1 << 30


def _load(name: str, path: Path):
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


# ------------------------------------------------------------------------------------------ data


def stadium():
    """(vb, mesh, crowd) of samples/stadium_crowd.py (numpy only; no USD needed)."""
    sample = _load("bench_stadium_crowd", ROOT / "samples" / "stadium_crowd.py")
    asset = sample.make_asset()
    vb = asset.animations[0]
    return vb, vb.meshes[0], asset.crowds[0]


def random_crowd(count: int, clip_count: int, seed: int = 7) -> Crowd:
    """``count`` instances on a grid with random yaw, clip offsets in [0, 10) s and rates in [0.9, 1.1]."""
    rng = np.random.default_rng(seed)
    side = int(np.ceil(np.sqrt(count)))
    grid = np.arange(count)
    positions = np.stack([(grid % side) * 0.6, np.zeros(count), (grid // side) * 0.85], axis=1)
    yaw = rng.uniform(-np.pi, np.pi, count)
    orientations = np.stack([np.zeros(count), np.sin(yaw / 2), np.zeros(count), np.cos(yaw / 2)], axis=1)
    return Crowd(path="/Bench/Crowd", positions=positions.astype(np.float32),
                 orientations=orientations.astype(np.float32),
                 clip=rng.integers(0, clip_count, count).astype(np.int32),
                 time_offset=rng.uniform(0.0, 10.0, count).astype(np.float32),
                 playback_rate=rng.uniform(0.9, 1.1, count).astype(np.float32))


def tiled_mesh(mesh: BoundMesh, vertex_count: int) -> BoundMesh:
    """The body repeated (shifted 1 m apart along x) until it has ``vertex_count`` vertices."""
    copies = -(-vertex_count // mesh.points.shape[0])
    shift = np.repeat(np.arange(copies, dtype=np.float32), mesh.points.shape[0])[:vertex_count]
    points = np.tile(mesh.points, (copies, 1))[:vertex_count].copy()
    points[:, 0] += shift
    return BoundMesh(path="/Bench/Big", points=points, face_vertex_counts=np.zeros(0, np.int32),
                     face_vertex_indices=np.zeros(0, np.int32),
                     bone_indices=np.tile(mesh.bone_indices, (copies, 1))[:vertex_count].copy(),
                     bone_weights=np.tile(mesh.bone_weights, (copies, 1))[:vertex_count].copy(),
                     normals=np.tile(mesh.normals, (copies, 1))[:vertex_count].copy())


def cases(names):
    vb, body, talk_crowd = stadium()
    out = []
    for name in names:
        if name == "talk":
            out.append((name, vb, body, talk_crowd))
        elif name == "crowd100k":
            out.append((name, vb, body, random_crowd(100_000, len(vb.clips))))
        elif name == "mesh50k":
            out.append((name, vb, tiled_mesh(body, 50_000), random_crowd(1_000, len(vb.clips), seed=8)))
        else:
            raise SystemExit(f"unknown case {name!r}")
    return out


def subset(crowd: Crowd, n: int, start: int = 0) -> Crowd:
    """Instances ``start .. start + n`` of a crowd."""
    s = slice(start, start + n)
    return Crowd(path=crowd.path, positions=crowd.positions[s], orientations=crowd.orientations[s],
                 clip=crowd.clip[s], time_offset=crowd.time_offset[s], playback_rate=crowd.playback_rate[s],
                 scales=None if crowd.scales is None else crowd.scales[s])


# ------------------------------------------------------------------------------------------ naive kernel


@wp.kernel
def naive_cross_matrix_kernel(
    texels: wp.array2d(dtype=wp.vec4),
    clip_first_row: wp.array(dtype=wp.int32),
    clip_row_count: wp.array(dtype=wp.int32),
    clip_rate: wp.array(dtype=wp.float64),
    clip_loop: wp.array(dtype=wp.int32),
    instance_clip: wp.array(dtype=wp.int32),
    instance_offset: wp.array(dtype=wp.float64),
    instance_rate: wp.array(dtype=wp.float64),
    t: wp.float64,
    points: wp.array(dtype=wp.vec3),
    normals: wp.array(dtype=wp.vec3),
    indices: wp.array2d(dtype=wp.int32),
    weights: wp.array2d(dtype=wp.float32),
    positions: wp.array(dtype=wp.vec3),
    orientations: wp.array(dtype=wp.quat),
    scales: wp.array(dtype=wp.vec3),
    out_points: wp.array2d(dtype=wp.vec3),
    out_normals: wp.array2d(dtype=wp.vec3),
):
    """Baseline: one thread per (instance, vertex) fetching and decoding each of its K bones."""
    instance, v = wp.tid()
    tau = instance_offset[instance] + instance_rate[instance] * t
    row0, row1, f = K.clip_rows(clip_first_row, clip_row_count, clip_rate, clip_loop, instance_clip[instance], tau)
    p = points[v]
    n = normals[v]
    sp = wp.vec3()
    sn = wp.vec3()
    for k in range(indices.shape[1]):
        column = indices[v, k] * 3
        w = weights[v, k]
        a = K.lerp_texel(texels, row0, row1, f, column)
        b = K.lerp_texel(texels, row0, row1, f, column + 1)
        c = K.lerp_texel(texels, row0, row1, f, column + 2)
        x = wp.vec3(a[0], a[1], a[2])
        y = wp.vec3(b[0], b[1], b[2])
        z = wp.cross(x, y)
        sp += w * (x * p[0] + y * p[1] + z * p[2] + wp.vec3(c[0], c[1], c[2]))
        sn += w * (x * n[0] + y * n[1] + z * n[2])
    q = orientations[instance]
    s = scales[instance]
    out_points[instance, v] = K.place_point(sp, positions[instance], q, s)
    out_normals[instance, v] = K.place_normal(wp.normalize(sn), q, s)


def launch_naive(decoder: wd.Decoder, crowd: wd.DeviceCrowd, t: float, out: wd.SkinResult) -> None:
    wp.launch(naive_cross_matrix_kernel, dim=(crowd.instance_count, decoder.vertex_count),
              inputs=[decoder.texels, decoder.clip_first_row, decoder.clip_row_count, decoder.clip_rate,
                      decoder.clip_loop, crowd.clip, crowd.time_offset, crowd.playback_rate, wp.float64(t),
                      decoder.points, decoder.normals, decoder.indices, decoder.weights, crowd.positions,
                      crowd.orientations, crowd.scales, out.points, out.normals], device=decoder.device)


@wp.kernel
def fill_outputs_kernel(instances_per_thread: int, out_points: wp.array2d(dtype=wp.vec3),
                        out_normals: wp.array2d(dtype=wp.vec3)):
    """Store ceiling: write every output of the skinning launch (same geometry), computing nothing."""
    j, v = wp.tid()
    first = j * instances_per_thread
    last = wp.min(first + instances_per_thread, out_points.shape[0])
    for instance in range(first, last):
        x = float(instance + v)
        out_points[instance, v] = wp.vec3(x, x, x)
        out_normals[instance, v] = wp.vec3(x, x, x)


@wp.kernel
def fill_padded_kernel(instances_per_thread: int, out: wp.array3d(dtype=wp.vec4)):
    """The same with 16-byte outputs (points and normals padded to float4): what the layout costs."""
    j, v = wp.tid()
    first = j * instances_per_thread
    last = wp.min(first + instances_per_thread, out.shape[1])
    for instance in range(first, last):
        x = float(instance + v)
        out[0, instance, v] = wp.vec4(x, x, x, 1.0)
        out[1, instance, v] = wp.vec4(x, x, x, 1.0)


# ------------------------------------------------------------------------------------------ timing


def time_cuda(fn, device, repeats: int, warmup: int = 2) -> float:
    """Seconds per call of ``fn`` (which launches on ``device``), from CUDA events."""
    for _ in range(warmup):
        fn()
    stream = wp.get_stream(device)
    start = wp.Event(device, enable_timing=True)
    end = wp.Event(device, enable_timing=True)
    stream.record_event(start)
    for _ in range(repeats):
        fn()
    stream.record_event(end)
    return wp.get_event_elapsed_time(start, end) / 1e3 / repeats


def time_host(fn, repeats: int, warmup: int = 1, device=None) -> float:
    """Seconds per call from the wall clock, synchronizing the device around the calls."""
    for _ in range(warmup):
        fn()
    if device is not None:
        wp.synchronize_device(device)
    start = time.perf_counter()
    for _ in range(repeats):
        fn()
    if device is not None:
        wp.synchronize_device(device)
    return (time.perf_counter() - start) / repeats


def copy_rate(device) -> float:
    """Device-to-device copy rate, bytes read + written per second (``wp.copy`` of 1 GiB)."""
    count = COPY_BYTES // 4
    src = wp.zeros(count, dtype=wp.float32, device=device)
    dst = wp.empty(count, dtype=wp.float32, device=device)
    seconds = time_cuda(lambda: wp.copy(dst, src), device, repeats=20, warmup=3)
    del src, dst
    return 2.0 * COPY_BYTES / seconds


def bytes_moved(decoder: wd.Decoder, instances: int) -> dict:
    """Bytes one ``skin_crowd`` call moves, by the counting in the module docstring."""
    v, b = decoder.vertex_count, decoder.bone_count
    k = int(decoder.indices.shape[1])
    outputs = instances * v * 24
    bone_bytes = {"crossMatrix": 48, "affineMatrix": 84, "quatTranslation": 84, "dualQuat": 32}[decoder.encoding.value]
    bones = 2 * instances * b * bone_bytes
    frame = wp.types.type_size_in_bytes(K.InstanceFrame)
    per_instance = instances * (20 + 40 + 2 * frame)
    mesh = v * (24 + 8 * k)
    texture = decoder.texels.capacity if decoder.texels is not None else decoder.vb.layout.texel_bytes
    return {"outputs": outputs, "bone_buffer": bones, "instance_inputs": per_instance, "mesh": mesh,
            "texture": int(texture), "total": outputs + bones + per_instance + mesh + int(texture)}


def agreement(decoder: wd.Decoder, vb, mesh, crowd: Crowd, t: float, limit: int) -> tuple:
    """(max position error / bounding-box diagonal, max normal error) against numpy, first ``limit`` instances."""
    part = subset(crowd, min(limit, crowd.instance_count))
    points, normals = decoder.skin_crowd(part, t).numpy()
    ref_points, ref_normals = reference.skin_crowd(vb, mesh, part, t)
    flat = ref_points.reshape(-1, 3)
    diag = float(np.linalg.norm(flat.max(axis=0) - flat.min(axis=0)))
    return float(np.abs(points - ref_points).max() / diag), float(np.abs(normals - ref_normals).max())


# ------------------------------------------------------------------------------------------ runs


def run_cuda(case_list, args) -> list:
    device = wp.get_device("cuda")
    rate = copy_rate(device)
    print(f"# {device.name}: device-to-device copy {rate / 1e9:.0f} GB/s (read + write)", flush=True)
    rows = []
    t = 3.7
    for name, vb, mesh, crowd in case_list:
        n, v = crowd.instance_count, mesh.points.shape[0]
        vi = n * v
        err = agreement(wd.Decoder(vb, mesh, device=device), vb, mesh, crowd, t, limit=1200 if n <= 1200 else 200)
        variants = [(1, 256), (4, 256), (8, 256), (16, 128), (16, 256), (16, 512), (32, 256)] if n >= 10_000 \
            or v >= 10_000 else [(1, 256), (16, 256)]
        for ipt, block in variants:
            decoder = wd.Decoder(vb, mesh, device=device, instances_per_thread=ipt, block_dim=block)
            uploaded = decoder.upload_crowd(crowd)
            out = decoder.allocate(n)
            counted = bytes_moved(decoder, n)
            total = time_cuda(lambda: decoder.skin_crowd(uploaded, t, out=out), device, args.repeats)
            buffers = decoder.decode_bones(uploaded, t)
            decode = time_cuda(lambda: decoder.decode_bones(uploaded, t), device, args.repeats)
            skin = time_cuda(lambda: decoder.skin_bones(uploaded, buffers, out), device, args.repeats)
            rows.append(dict(case=name, device="cuda", method=f"warp: bones, then skin ({ipt} inst/thr, {block})",
                             instances_per_thread=ipt, block_dim=block, instances=n, vertices=v, seconds=total,
                             decode_seconds=decode, skin_seconds=skin, vertex_instances_per_second=vi / total,
                             bytes=counted, bytes_per_second=counted["total"] / total,
                             fraction_of_copy=counted["total"] / total / rate,
                             fraction_outputs=counted["outputs"] / total / rate,
                             copy_bytes_per_second=rate, max_error_of_diagonal=err[0], max_normal_error=err[1]))
            print(_row_text(rows[-1]), flush=True)
            del decoder, uploaded, out, buffers
        decoder = wd.Decoder(vb, mesh, device=device)
        uploaded = decoder.upload_crowd(crowd)
        out = decoder.allocate(n)
        ipt = decoder._instances_per_thread(n)
        dim = (-(-n // ipt), v)
        fill = time_cuda(lambda: wp.launch(fill_outputs_kernel, dim=dim, inputs=[ipt, out.points, out.normals],
                                           device=device), device, args.repeats)
        rows.append(dict(case=name, device="cuda", method="store ceiling: write float3 outputs only",
                         instances=n, vertices=v, seconds=fill, vertex_instances_per_second=vi / fill,
                         bytes_per_second=counted["outputs"] / fill, fraction_of_copy=counted["outputs"] / fill / rate,
                         fraction_outputs=counted["outputs"] / fill / rate, copy_bytes_per_second=rate))
        print(_row_text(rows[-1]), flush=True)
        padded = wp.empty((2, n, v), dtype=wp.vec4, device=device)
        fill4 = time_cuda(lambda: wp.launch(fill_padded_kernel, dim=dim, inputs=[ipt, padded], device=device),
                          device, args.repeats)
        rows.append(dict(case=name, device="cuda", method="store ceiling: float4-padded outputs",
                         instances=n, vertices=v, seconds=fill4, vertex_instances_per_second=vi / fill4,
                         bytes_per_second=32 * vi / fill4, fraction_of_copy=32 * vi / fill4 / rate,
                         fraction_outputs=counted["outputs"] / fill4 / rate, copy_bytes_per_second=rate))
        print(_row_text(rows[-1]), flush=True)
        del padded
        naive = time_cuda(lambda: launch_naive(decoder, uploaded, t, out), device, args.repeats)
        naive_points = out.points.numpy()[:50]
        good = decoder.skin_crowd(uploaded, t, out=out).points.numpy()[:50]
        rows.append(dict(case=name, device="cuda", method="warp naive (1 kernel, decode per vertex)",
                         instances=n, vertices=v, seconds=naive, vertex_instances_per_second=vi / naive,
                         bytes_per_second=counted["outputs"] / naive,
                         fraction_outputs=counted["outputs"] / naive / rate, copy_bytes_per_second=rate,
                         naive_max_difference=float(np.abs(naive_points - good).max())))
        print(_row_text(rows[-1]), flush=True)
        hardware = wd.Decoder(vb, mesh, device=device, sampling="hardware")
        up_hw = hardware.upload_crowd(crowd)
        counted_hw = bytes_moved(hardware, n)
        hw = time_cuda(lambda: hardware.skin_crowd(up_hw, t, out=out), device, args.repeats)
        hw_points = out.points.numpy()
        exact_points = decoder.skin_crowd(uploaded, t).points.numpy()
        flat = exact_points.reshape(-1, 3)
        diag = float(np.linalg.norm(flat.max(axis=0) - flat.min(axis=0)))
        rows.append(dict(case=name, device="cuda", method="warp hardware texture path", instances=n, vertices=v,
                         seconds=hw, vertex_instances_per_second=vi / hw, bytes=counted_hw,
                         bytes_per_second=counted_hw["total"] / hw, fraction_of_copy=counted_hw["total"] / hw / rate,
                         fraction_outputs=counted_hw["outputs"] / hw / rate, copy_bytes_per_second=rate,
                         hardware_vs_exact_of_diagonal=float(np.abs(hw_points - exact_points).max() / diag)))
        print(_row_text(rows[-1]), flush=True)
        del decoder, uploaded, out, hardware, up_hw
    return rows


def run_cpu(case_list, args) -> list:
    rows = []
    t = 3.7
    for name, vb, mesh, crowd in case_list:
        n, v = crowd.instance_count, mesh.points.shape[0]
        decoder = wd.Decoder(vb, mesh, device="cpu")
        uploaded = decoder.upload_crowd(crowd)
        out = decoder.allocate(n)
        repeats = 5 if n * v <= 1_000_000 else 1
        seconds = time_host(lambda: decoder.skin_crowd(uploaded, t, out=out), repeats, device="cpu")
        rows.append(dict(case=name, device="cpu", method="warp cpu", instances=n, vertices=v, seconds=seconds,
                         vertex_instances_per_second=n * v / seconds))
        print(_row_text(rows[-1]), flush=True)
        # numpy's memory grows with instances x vertices x K x 9 float64: time it on chunks of at
        # most ~1 M vertex-instances and report the rate (throughput is flat in instance count).
        chunk = max(1, min(n, 1_000_000 // v))
        measured = min(n, chunk * (1 if n * v > 1_000_000 else max(1, n // chunk)))
        parts = [subset(crowd, chunk, s) for s in range(0, measured, chunk)]
        start = time.perf_counter()
        for part in parts:
            reference.skin_crowd(vb, mesh, part, t)
        numpy_seconds = time.perf_counter() - start
        done = sum(p.instance_count for p in parts)
        rows.append(dict(case=name, device="cpu", method=f"numpy reference ({done} instances timed)",
                         instances=n, vertices=v, seconds=numpy_seconds * n / done,
                         vertex_instances_per_second=done * v / numpy_seconds))
        print(_row_text(rows[-1]), flush=True)
        del decoder, uploaded, out
    return rows


def _row_text(row: dict) -> str:
    fraction = row.get("fraction_of_copy")
    fraction_text = "" if fraction is None else f"{100 * fraction:5.1f}%"
    return (f"| {row['case']:9} | {row['instances']:>7,} x {row['vertices']:>6,} | {row['device']:4} | "
            f"{row['method']:44} | {row['seconds'] * 1e3:9.3f} | {row['vertex_instances_per_second'] / 1e6:11,.1f} | "
            f"{fraction_text:>6} | {100 * row.get('fraction_outputs', float('nan')):5.1f}% |"
            if "fraction_outputs" in row else
            f"| {row['case']:9} | {row['instances']:>7,} x {row['vertices']:>6,} | {row['device']:4} | "
            f"{row['method']:44} | {row['seconds'] * 1e3:9.3f} | {row['vertex_instances_per_second'] / 1e6:11,.1f} | "
            f"{'':>6} | {'':>6} |")


# ------------------------------------------------------------------------------------------ hardware study


@wp.kernel
def probe_kernel(texture: wp.Texture2D, fractions: wp.array(dtype=wp.float32), out: wp.array(dtype=wp.vec4)):
    """Sample a 1-texel-wide, 2-row texture holding 0 then 1 at ``v = 0.5 + f``: returns the weight."""
    i = wp.tid()
    out[i] = wp.texture_sample(texture, wp.vec2f(0.5, 0.5 + fractions[i]), dtype=wp.vec4f)


def probe_filter_weights(device, dtype) -> dict:
    """The texture unit's vertical filter weight against the exact fraction, on a fine grid."""
    data = np.zeros((2, 1, 4), dtype=dtype)
    data[1] = np.iinfo(dtype).max if np.issubdtype(dtype, np.integer) else 1
    texture = wp.Texture2D(data, filter_mode=wp.TextureFilterMode.LINEAR, address_mode=wp.TextureAddressMode.CLAMP,
                           normalized_coords=False, device=device)
    f = (np.arange(65536, dtype=np.float64) / 65536).astype(np.float32)
    out = wp.zeros(f.shape[0], dtype=wp.vec4, device=device)
    wp.launch(probe_kernel, dim=f.shape[0], inputs=[texture, wp.array(f, dtype=wp.float32, device=device), out],
              device=device)
    weight = out.numpy()[:, 0].astype(np.float64)
    f64 = f.astype(np.float64)
    return {"texel_dtype": np.dtype(dtype).name, "distinct_weights": int(np.unique(weight).size),
            "max_abs_weight_error": float(np.abs(weight - f64).max()),
            "max_diff_to_round_256": float(np.abs(weight - np.round(f64 * 256) / 256).max()),
            "max_diff_to_floor_256": float(np.abs(weight - np.floor(f64 * 256) / 256).max())}


@wp.kernel
def probe_grid_kernel(texture: wp.Texture2D, fractions: wp.array(dtype=wp.float32), out: wp.array2d(dtype=wp.vec4)):
    """Sample every column of a 2-row texture at ``v = 0.5 + f`` for each fraction f."""
    i, column = wp.tid()
    out[i, column] = wp.texture_sample(texture, wp.vec2f(float(column) + 0.5, 0.5 + fractions[i]), dtype=wp.vec4f)


def probe_filter_arithmetic(device, dtype, seed: int = 11) -> dict:
    """Is the filtered value ``(1 - w) a + w b`` computed in float32, or rounded to the texel format?

    Random texel pairs in [-2, 2]; for each returned value the weight ``w`` is taken as the multiple
    of 1/256 nearest to f that best explains it; reports the residual after that and how many
    results are exactly representable in float16 (all of them if the unit filters in half).
    """
    rng = np.random.default_rng(seed)
    data = rng.uniform(-2.0, 2.0, size=(2, 64, 4)).astype(dtype)
    texture = wp.Texture2D(data, filter_mode=wp.TextureFilterMode.LINEAR, address_mode=wp.TextureAddressMode.CLAMP,
                           normalized_coords=False, device=device)
    f = ((np.arange(1024) + 0.37) / 1024).astype(np.float32)
    out = wp.zeros((f.shape[0], 64), dtype=wp.vec4, device=device)
    wp.launch(probe_grid_kernel, dim=out.shape, inputs=[texture, wp.array(f, dtype=wp.float32, device=device), out],
              device=device)
    got = out.numpy().astype(np.float64)  # (F, 64, 4)
    a, b = data[0].astype(np.float64), data[1].astype(np.float64)
    best = np.full(got.shape, np.inf)
    for step in (-1, 0, 1):
        w = ((np.round(f.astype(np.float64) * 256) + step) / 256)[:, None, None]
        best = np.minimum(best, np.abs(got - ((1 - w) * a + w * b)))
    exact = (1 - f.astype(np.float64)[:, None, None]) * a + f.astype(np.float64)[:, None, None] * b
    return {"texel_dtype": np.dtype(dtype).name,
            "max_residual_after_256_weights": float(best.max()),
            "max_error_vs_exact_fraction": float(np.abs(got - exact).max()),
            "fraction_float16_representable": float(np.mean(got.astype(np.float16).astype(np.float64) == got))}


def hardware_study(device: str) -> dict:
    """Exact vs hardware texture path for every encoding x texel format, plus the weight probe."""
    synthetic = _load("bench_warp_synthetic", ROOT / "tests" / "helpers" / "warp_synthetic.py")
    probes = [probe_filter_weights(device, d) for d in (np.float16, np.float32, np.uint16)]
    probes += [probe_filter_arithmetic(device, d) for d in (np.float16, np.float32)]
    for probe in probes:
        print(f"# probe {probe}", flush=True)
    rows = []
    tau = np.linspace(0.0, 1.0, 2001)  # 2,001 times across the looping clip, wrap included

    def measure(label, vb, clip_index, times):
        exact = wd.Decoder(vb, device=device)
        hardware = wd.Decoder(vb, device=device, sampling="hardware")
        want, want_n = exact.skin(clip_index, times).numpy()
        got, got_n = hardware.skin(clip_index, times).numpy()
        diag = float(np.linalg.norm(want.reshape(-1, 3).max(0) - want.reshape(-1, 3).min(0)))
        row = {"case": label, "diagonal": diag, "hardware_vs_exact": float(np.abs(got - want).max() / diag),
               "hardware_vs_exact_normal": float(np.abs(got_n - want_n).max())}
        for name, steps in (("round_256", 256), ("floor_256", -256)):
            model = exact.skin(clip_index, times, fraction_steps=steps).numpy()[0]
            row[f"model_{name}_vs_exact"] = float(np.abs(model - want).max() / diag)
            row[f"hardware_vs_model_{name}"] = float(np.abs(got - model).max() / diag)
        rows.append(row)
        print(f"# {label:34} diag {diag:6.3f}  hw-exact {row['hardware_vs_exact']:.2e}  "
              f"hw-round256 {row['hardware_vs_model_round_256']:.2e}  hw-floor256 "
              f"{row['hardware_vs_model_floor_256']:.2e}  normals {row['hardware_vs_exact_normal']:.2e}", flush=True)

    for encoding in ("crossMatrix", "affineMatrix", "quatTranslation", "dualQuat"):
        for texel_format in ("float16", "float32", "unorm16"):
            measure(f"synthetic {encoding} {texel_format}", synthetic.make_vb(encoding, texel_format), 0, tau)
    vb, _, _ = stadium()
    measure("stadium crossMatrix float16", vb, 0, np.linspace(0.0, 10.0, 2001))
    return {"probes": probes, "rows": rows}


HEADER = ("| case      | instances x vertices | dev  | method                                       |   ms/call |    M vi/s | "
          "% copy | % copy (outputs) |\n"
          "|---|---|---|---|---:|---:|---:|---:|")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--devices", default=",".join(wd.available_devices()))
    parser.add_argument("--cases", default="talk,crowd100k,mesh50k")
    parser.add_argument("--repeats", type=int, default=20, help="timed calls per CUDA measurement")
    parser.add_argument("--json", type=Path, help="write the rows here")
    parser.add_argument("--hardware", action="store_true",
                        help="measure the hardware texture path against the exact path instead")
    args = parser.parse_args(argv)
    if args.hardware:
        result = {d: hardware_study(d) for d in args.devices.split(",")}
        if args.json:
            _write_json(args.json, {"warp": wp.__version__, "devices": _device_names(args.devices.split(",")),
                                    "study": result})
        return 0
    case_list = cases(args.cases.split(","))
    print(HEADER, flush=True)
    rows = []
    for device in args.devices.split(","):
        if device == "cuda":
            rows += run_cuda(case_list, args)
        elif device == "cpu":
            rows += run_cpu(case_list, args)
        else:
            raise SystemExit(f"unknown device {device!r}")
    if args.json:
        _write_json(args.json, {"warp": wp.__version__, "python": platform.python_version(),
                                "devices": _device_names(args.devices.split(",")),
                                "rows": rows})
    return 0


def _write_json(path: Path, data: dict) -> None:
    """Write the results through vbusd.io.files.atomic_write: no partial results file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path, "w") as stream:
        json.dump(data, stream, indent=1)


def _device_names(devices) -> dict:
    """``{"cuda": "NVIDIA H100 80GB HBM3", ...}``: which hardware the results came from."""
    return {d: str(wp.get_device(d).name) for d in devices}


if __name__ == "__main__":
    sys.exit(main())

"""vbusd's three.js and Babylon.js runtimes beside each engine's own way, same character, same browser (issue 27).

What it runs: a Khronos glTF character (default CesiumMan, from ``$VBUSD_SHARED_ASSETS`` or
``../shared/assets``; copied to a temporary folder for the run only) converted with
``vbusd convert --loop`` (its walk is a cycle) and placed ``N`` times with ``vbusd crowd`` (grid, one clip, random time offsets
and yaws, rate 1), then drawn in headless Chromium by:

* ``vbusd (WebGPU, TSL)``: ``vbusd view --engine three-webgpu``: WebGPURenderer on WebGPU
  (SwiftShader's Vulkan), one InstancedMesh, the skinning as TSL (web/src/webgpu);
* ``vbusd (WebGL)``: ``vbusd view`` (WebGLRenderer, the GLSL runtime), with ``--engines three``;
* ``three clones``: three.js r187's own way on the same page and renderer. r187 has no
  ``InstancedSkinnedMesh`` (it was merged after r187), so its closest equivalent is one
  ``SkinnedMesh`` per instance: ``SkeletonUtils.clone`` of the glTF scene, an ``AnimationMixer``
  per clone set to the instance's clip time every frame, placed by the crowd's instance matrix;
* ``vbusd (Babylon plugin)``: ``vbusd view --engine babylon``, with ``--engines babylon``: Babylon.js
  9.28 on WebGL 2, one Mesh with thin instances skinned by the material plugin (web/babylon);
* ``Babylon BVA``: Babylon's own baked animation on the same page and engine: the same glTF
  loaded by Babylon's glTF loader, its skin baked into a ``VertexAnimationBaker`` texture (a
  float32 4x4 matrix per bone and frame, as many frames as vbusd's rows, at vbusd's rows per
  second; the frames are posed by driving the glTF's AnimationGroup, since the baker's own
  ``bakeVertexData`` drives skeleton animations, which glTF skins do not have, then read with
  ``skeleton.getTransformMatrices`` as the baker does), drawn by ``BakedVertexAnimationManager``
  on thin instances with per-instance (start, end, offset, fps); no interpolation between frames.
  Its pose is evaluated on the CPU with the manager's shader formula (frame number from time,
  offset and fps; linear blend of the baked matrices) on its texture data.

Figures, per engine and count: animation bytes on the GPU (vbusd: the texture plus the
per-instance data; clones: one bone-matrix buffer per instance, re-uploaded every frame, the
keyframes staying on the CPU), CPU time per frame (the JavaScript of advancing the clock and
``render()``, not waiting for the GPU), frame time (rendered and finished: the GPU queue drained),
and the pose difference at chosen times (the vbusd probe's world vertices against three's own
CPU skinning of the clone, ``SkinnedMesh.getVertexPosition``: the largest distance from a vertex
of one to the nearest vertex of the other, over the bounding-box diagonal).

SOFTWARE rendering: SwiftShader runs every vertex and fragment on the CPU (2 shared cores here),
so frame times are orders of magnitude above a GPU's; they compare the methods on one rasterizer.

Usage::

    python benchmarks/engines_side_by_side.py [--character CesiumMan] [--counts 1000 10000] [--frames 3]
        [--engines three-webgpu three babylon]
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import tempfile
from pathlib import Path

import numpy as np

import vbusd
from tests.helpers.browser import evaluate_arrays, read_probe
from vbusd.web.browser import ViewerPage, chromium, unavailable_reason
from vbusd.web.server import ViewerServer

REPO = Path(__file__).resolve().parents[2]
WIDTH, HEIGHT = 1280, 720
PROBE_TIMES = (0.0, 0.37, 1.21)

MEASURE = """async ([frames, method, url]) => {
  const v = window.vbusd;
  const THREE = await import('three');
  const finish = async () => {
    const backend = v.renderer.backend;
    if (backend?.isWebGPUBackend) return backend.device.queue.onSubmittedWorkDone();
    const gl = backend?.gl ?? v.renderer.getContext();
    gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, new Uint8Array(4));
  };
  const crowd = v.crowds[0];
  let advance = (t) => v.setTime(t);
  let bytes = 0;
  const animation = v.animations[0];
  const layout = animation.layout;
  const texelBytes = { float16: 2, float32: 4, unorm16: 2 }[layout.texelFormat];
  if (method === 'vbusd') {
    bytes = layout.width * layout.height * 4 * texelBytes + crowd.count * (64 + 4 + 8 + 4 + 12);
  } else {
    const { GLTFLoader } = await import('three/addons/loaders/GLTFLoader.js');
    const SkeletonUtils = await import('three/addons/utils/SkeletonUtils.js');
    const gltf = await new GLTFLoader().loadAsync(url);
    const clip = gltf.animations[0];
    for (const c of v.crowds) c.visible = false;
    const group = new THREE.Group();
    v.scene.add(group);
    const clones = [];
    crowd.updateMatrixWorld(true);
    for (let i = 0; i < crowd.count; ++i) {
      const clone = SkeletonUtils.clone(gltf.scene);
      clone.matrixAutoUpdate = false;
      clone.matrix.multiplyMatrices(crowd.matrixWorld, new THREE.Matrix4().fromArray(crowd.instanceMatrix.array, 16 * i));
      const mixer = new THREE.AnimationMixer(clone);
      mixer.clipAction(clip).play();
      clone.traverse((o) => { if (o.isSkinnedMesh) { o.frustumCulled = false; o.castShadow = o.receiveShadow = true; bytes += o.skeleton.bones.length * 64; } });
      group.add(clone);
      clones.push({ clone, mixer, offset: crowd.timeAttribute.array[2 * i], rate: crowd.timeAttribute.array[2 * i + 1] });
    }
    // The same clip time: clip-local tau wraps with the baked clip's period (rowCount / rowsPerSecond:
    // the glTF keys' span), and is source time startTime + tau (spec: Clips). The mixer's own loop
    // would wrap at the clip's duration from 0, a different period.
    const { startTime, rowCount, rowsPerSecond } = animation.clips[0];
    const period = rowCount / rowsPerSecond;
    window.vbusdSourceTime = (tau) => startTime + (tau - period * Math.floor(tau / period));
    advance = (t) => {
      v.setTime(t);
      for (const c of clones) c.mixer.setTime(window.vbusdSourceTime(c.offset + c.rate * t));
    };
    window.vbusdClones = clones;
  }
  let t = 1.0;
  advance(t); v.render(); await finish();  // compile and warm up
  advance(t += 1 / 60); v.render(); await finish();
  let cpu = 0;
  const start = performance.now();
  for (let i = 0; i < frames; ++i) {
    const begin = performance.now();
    advance(t += 1 / 60);
    v.render();
    cpu += performance.now() - begin;
    await finish();
  }
  return { frame: (performance.now() - start) / frames, cpu: cpu / frames, bytes };
}"""

# three's own CPU skinning of clone `i` at time t: world positions of every skinned vertex.
CLONE_POSE = """([i, t]) => {
  const c = window.vbusdClones[i];
  c.mixer.setTime(window.vbusdSourceTime(c.offset + c.rate * t));
  c.clone.updateMatrixWorld(true);
  const out = [];
  c.clone.traverse((o) => {
    if (!o.isSkinnedMesh) return;
    o.skeleton.update();
    const p = new o.position.constructor();
    for (let k = 0; k < o.geometry.attributes.position.count; ++k) {
      o.getVertexPosition(k, p);
      p.applyMatrix4(o.matrixWorld);
      out.push(p.x, p.y, p.z);
    }
  });
  return out;
}"""


MEASURE_BABYLON = """async ([frames, method, url]) => {
  const v = window.vbusd;
  const B = await import('@babylonjs/core');
  const { scene, engine } = v.babylon;
  const gl = engine._gl;
  const finish = () => gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, new Uint8Array(4));
  const crowd = v.crowds[0];
  const animation = v.animations[0];
  const layout = animation.layout;
  const texelBytes = { float16: 2, float32: 4 }[layout.texelFormat];
  engine.stopRenderLoop();
  let advance = (t) => v.setTime(t);
  let bytes = 0;
  if (method === 'vbusd') {
    bytes = layout.width * layout.height * 4 * texelBytes + crowd.count * (64 + 32);
  } else {
    for (const m of crowd.meshes) m.setEnabled(false);
    const result = await B.ImportMeshAsync(url, scene);
    const mesh = result.meshes.find((m) => m.skeleton && m.getTotalVertices() > 0);
    const group = result.animationGroups[0];
    const skeleton = mesh.skeleton;
    // Thin instances are placed by the vbusd crowd's matrices, which apply after the character's own
    // world transform W (its glTF node hierarchy, as vbusd converted it): W is baked into every bone
    // matrix (row vectors: M W) and the mesh gets the identity, so instance i draws p M W P_i.
    const W = mesh.computeWorldMatrix(true).clone();
    mesh.parent = null;
    mesh.position.setAll(0);
    mesh.rotationQuaternion = null;
    mesh.rotation.setAll(0);
    mesh.scaling.setAll(1);
    const { startTime, rowCount, rowsPerSecond } = animation.clips[0];
    const fps = group.targetedAnimations[0].animation.framePerSecond;
    const per = (skeleton.bones.length + 1) * 16;
    const data = new Float32Array(per * rowCount);
    group.start(false);
    group.pause();
    for (let k = 0; k < rowCount; ++k) {  // the baker's loop, posing through the AnimationGroup
      group.goToFrame((startTime + k / rowsPerSecond) * fps);
      scene.render();
      skeleton.computeAbsoluteMatrices(true);
      const matrices = skeleton.getTransformMatrices(mesh);
      for (let b = 0; b < per / 16; ++b) B.Matrix.FromArray(matrices, 16 * b).multiply(W).copyToArray(data, k * per + 16 * b);
    }
    group.stop();
    const baker = new B.VertexAnimationBaker(scene, mesh);
    const texture = baker.textureFromBakedVertexData(data);
    const manager = new B.BakedVertexAnimationManager(scene);
    manager.texture = texture;
    mesh.bakedVertexAnimationManager = manager;
    const settings = new Float32Array(4 * crowd.count);
    for (let i = 0; i < crowd.count; ++i) {
      settings.set([0, rowCount - 1, crowd.instanceA[4 * i + 1] * rowsPerSecond, rowsPerSecond * crowd.instanceA[4 * i + 2]], 4 * i);
    }
    mesh.thinInstanceSetBuffer('matrix', crowd.matrices.slice(0, 16 * crowd.count), 16, true);
    mesh.thinInstanceSetBuffer('bakedVertexAnimationSettingsInstanced', settings, 4, true);
    mesh.alwaysSelectAsActiveMesh = true;
    v.babylon.shadowGenerator?.addShadowCaster(mesh);
    bytes = data.byteLength + crowd.count * (64 + 16);
    advance = (t) => { v.setTime(t); manager.time = t; };
    window.vbusdBVA = { mesh, data, per, settings, manager };
    await scene.whenReadyAsync();
  }
  let t = 1.0;
  advance(t); v.render(); finish();  // compile and warm up
  advance(t += 1 / 60); v.render(); finish();
  let cpu = 0;
  const start = performance.now();
  for (let i = 0; i < frames; ++i) {
    const begin = performance.now();
    advance(t += 1 / 60);
    v.render();
    cpu += performance.now() - begin;
    finish();
  }
  return { frame: (performance.now() - start) / frames, cpu: cpu / frames, bytes };
}"""

# Babylon's BakedVertexAnimationManager pose of instance i at time t, on the CPU: the frame number
# by its shader's formula (bakedVertexAnimation.fx), the baked matrices blended by the mesh's own
# matricesIndices / matricesWeights, then the thin instance's matrix and the mesh's world matrix.
BVA_POSE = """([i, t]) => {
  const { mesh, data, per, settings } = window.vbusdBVA;
  const [startFrame, endFrame, offsetFrame, speed] = settings.subarray(4 * i, 4 * i + 4);
  const totalFrames = endFrame - startFrame + 1;
  const time = t * speed / totalFrames;
  const correction = time < 1 ? 0 : 1;
  const frames = totalFrames - correction;
  const fract = time - Math.floor(time);
  let frame = fract * frames + offsetFrame;
  frame = frame - frames * Math.floor(frame / frames);
  frame = Math.floor(frame) + startFrame + correction;
  const positions = mesh.getVerticesData('position');
  const sets = [['matricesIndices', 'matricesWeights'], ['matricesIndicesExtra', 'matricesWeightsExtra']]
    .map(([a, b]) => [mesh.getVerticesData(a), mesh.getVerticesData(b)]).filter(([a]) => a);
  const instance = mesh.thinInstanceGetWorldMatrices()[i];
  const world = instance.multiply(mesh.computeWorldMatrix(true)).m;
  const out = [];
  for (let v = 0; v < positions.length / 3; ++v) {
    const m = new Float64Array(16);
    for (const [indices, weights] of sets) for (let k = 0; k < 4; ++k) {
      const w = weights[4 * v + k];
      if (!w) continue;
      const base = frame * per + 16 * indices[4 * v + k];
      for (let e = 0; e < 16; ++e) m[e] += w * data[base + e];
    }
    const [x, y, z] = positions.subarray(3 * v, 3 * v + 3);
    const p = [0, 1, 2].map((c) => x * m[c] + y * m[4 + c] + z * m[8 + c] + m[12 + c]);
    out.push(...[0, 1, 2].map((c) => p[0] * world[c] + p[1] * world[4 + c] + p[2] * world[8 + c] + world[12 + c]));
  }
  return out;
}"""


def character_source(name: str) -> Path:
    """The character's .glb among the shared assets."""
    root = Path(os.environ.get("VBUSD_SHARED_ASSETS", REPO.parent / "shared" / "assets"))
    found = sorted((root / "gltf" / name).rglob("*.glb"))
    if not found:
        raise SystemExit(f"engines_side_by_side: no {name} .glb under {root / 'gltf'} (set VBUSD_SHARED_ASSETS)")
    return found[0]


def build_crowd(source: Path, folder: Path, count: int) -> Path:
    """The character converted and placed ``count`` times (one clip, random offsets and yaws)."""
    from vbusd.cli import main as cli

    character = folder / "character" / "character.usda"
    if not character.exists():
        character.parent.mkdir(parents=True)
        shutil.copy(source, character.parent / "source.glb")
        vbusd.convert(character.parent / "source.glb", character, vbusd.ConvertOptions(check_rows=0, loop=True))
    clip = vbusd.read_asset(character).animations[0].clips[0].name
    crowd = folder / f"crowd_{count}" / "crowd.usda"
    crowd.parent.mkdir(parents=True)
    shutil.copy(source, crowd.parent / "source.glb")
    status = cli(["crowd", str(character), "-o", str(crowd), "--count", str(count), "--clips", clip,
                  "--seed", "27", "--allow-outside-paths", "-q"])
    if status:
        raise SystemExit(f"engines_side_by_side: vbusd crowd failed ({status})")
    return crowd


def pose_difference(page, instance: int, t: float, theirs_script: str = CLONE_POSE) -> float:
    """Largest nearest-vertex distance between vbusd's probe and the engine's own pose (three's CPU
    skinning of the clone, or Babylon's BVA evaluated on the CPU), over the bounding-box diagonal
    (symmetric)."""
    ours = np.asarray(read_probe(page.page, instance, t)["positions"]).reshape(-1, 3)
    theirs = evaluate_arrays(page.page, f"async (arg) => ({{positions: await ({theirs_script})(arg)}})", [instance, t],
                             ["positions"])["positions"].reshape(-1, 3)
    # Every pairwise squared distance as |a|^2 + |b|^2 - 2 a.b (one matrix product, milliseconds where
    # the (V, V', 3) differences took seconds); its rounding (~1e-15 of |a|^2) is far below the 5e-3
    # and 2e-2 of the diagonal the measure separates.
    center = ours.mean(0)  # near the origin, where |a|^2 rounds least
    ours, theirs = ours - center, theirs - center
    squared = (ours ** 2).sum(1)[:, None] + (theirs ** 2).sum(1)[None, :] - 2.0 * ours @ theirs.T
    # The nearest distances are the roots of the least squares (the root is monotonic): two roots per
    # vertex, not one per pair.
    ours_nearest = np.sqrt(np.maximum(squared.min(1), 0.0))
    theirs_nearest = np.sqrt(np.maximum(squared.min(0), 0.0))
    worst = max(ours_nearest.max(), theirs_nearest.max())
    return float(worst / np.linalg.norm(theirs.max(0) - theirs.min(0)))


def run(browser, crowd: Path, engine: str, method: str, frames: int) -> dict:
    query = f"?ui=0&paused=1&time=1.0&pixelRatio=1&width={WIDTH}&height={HEIGHT}"
    with ViewerServer(crowd, engine=engine, allow_outside_paths=True) as server:
        page = ViewerPage(browser, server.url + query, width=WIDTH, height=HEIGHT, timeout_s=600)
        try:
            if page.error:
                raise RuntimeError(page.error)
            page.page.set_default_timeout(3_600_000)
            measure = MEASURE_BABYLON if engine == "babylon" else MEASURE
            result = page.page.evaluate(measure, [frames, method, server.url + "asset/source.glb"])
            if method == "clones":
                result["pose"] = max(pose_difference(page, 0, t) for t in PROBE_TIMES)
            if method == "bva":
                result["pose"] = max(pose_difference(page, 0, t, BVA_POSE) for t in PROBE_TIMES)
            errors = page.errors()
            if errors:
                raise RuntimeError(errors)
            result["picture"] = page.page.locator("#view").screenshot()
        finally:
            page.close()
    return result


def main() -> None:
    """Print the side-by-side table (markdown); save one picture per method under --pictures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--character", default="CesiumMan")
    parser.add_argument("--counts", type=int, nargs="+", default=[1000, 10000])
    parser.add_argument("--frames", type=int, default=3)
    parser.add_argument("--engines", nargs="+", default=["three-webgpu"], choices=["three-webgpu", "three", "babylon"])
    parser.add_argument("--pictures", type=Path, default=None, help="folder for a screenshot of each method")
    args = parser.parse_args()
    reason = unavailable_reason()
    if reason:
        raise SystemExit(f"engines_side_by_side: {reason}")
    source = character_source(args.character)
    with tempfile.TemporaryDirectory() as folder, chromium(webgpu=True) as browser:
        print(f"SOFTWARE rendering (SwiftShader), Chromium {browser.version}, {platform.machine()}, {os.cpu_count()} CPUs, "
              f"load average {os.getloadavg()[0]:.1f} at the start; {args.character}, {WIDTH} x {HEIGHT}, "
              f"lit + shadows, {args.frames} frames each")
        print("| engine | method | instances | animation bytes on the GPU | CPU per frame (ms) | frame time (ms) "
              "| pose difference (of the diagonal) |")
        print("| --- | --- | ---: | ---: | ---: | ---: | ---: |")
        for count in args.counts:
            crowd = build_crowd(source, Path(folder), count)
            for engine in args.engines:
                for method in ("vbusd", "bva") if engine == "babylon" else ("vbusd", "clones"):
                    result = run(browser, crowd, engine, method, args.frames)
                    label = {"three-webgpu": "three.js WebGPURenderer (WebGPU)", "three": "three.js WebGLRenderer",
                             "babylon": "Babylon.js 9.28 (WebGL 2)"}[engine]
                    name = {("three-webgpu", "vbusd"): "vbusd (TSL)", ("three", "vbusd"): "vbusd (GLSL)",
                            ("babylon", "vbusd"): "vbusd (material plugin)",
                            ("babylon", "bva"): "BakedVertexAnimationManager"}.get((engine, method), "SkinnedMesh clones")
                    pose = f"{result['pose']:.2e}" if "pose" in result else "reference"
                    print(f"| {label} | {name} | {count:,} | {result['bytes']:,} | {result['cpu']:.1f} | "
                          f"{result['frame']:.1f} | {pose} |", flush=True)
                    if args.pictures:
                        args.pictures.mkdir(parents=True, exist_ok=True)
                        (args.pictures / f"side_by_side_{engine}_{method}_{count}.png").write_bytes(result["picture"])


if __name__ == "__main__":
    main()

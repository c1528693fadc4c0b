"""vbusd's three.js runtimes beside three.js' own way, same character, same browser (issue 27).

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
  per clone set to the instance's clip time every frame, placed by the crowd's instance matrix.

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
        [--engines three-webgpu three]
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
from vbusd.web.browser import ViewerPage, chromium, unavailable_reason
from vbusd.web.server import ViewerServer

REPO = Path(__file__).resolve().parents[1]
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


def pose_difference(page, instance: int, t: float) -> float:
    """Largest nearest-vertex distance between vbusd's probe and three's CPU skinning, over the
    bounding-box diagonal (symmetric)."""
    ours = np.asarray(page.page.evaluate("([i, t]) => window.vbusd.probe(i, t)", [instance, t])["positions"]).reshape(-1, 3)
    theirs = np.asarray(page.page.evaluate(CLONE_POSE, [instance, t])).reshape(-1, 3)
    distances = np.sqrt(((ours[:, None, :] - theirs[None, :, :]) ** 2).sum(-1))
    worst = max(distances.min(1).max(), distances.min(0).max())
    return float(worst / np.linalg.norm(theirs.max(0) - theirs.min(0)))


def run(browser, crowd: Path, engine: str, method: str, frames: int) -> dict:
    query = f"?ui=0&paused=1&time=1.0&pixelRatio=1&width={WIDTH}&height={HEIGHT}"
    with ViewerServer(crowd, engine=engine, allow_outside_paths=True) as server:
        page = ViewerPage(browser, server.url + query, width=WIDTH, height=HEIGHT, timeout_s=600)
        try:
            if page.error:
                raise RuntimeError(page.error)
            page.page.set_default_timeout(3_600_000)
            result = page.page.evaluate(MEASURE, [frames, method, server.url + "asset/source.glb"])
            if method == "clones":
                result["pose"] = max(pose_difference(page, 0, t) for t in PROBE_TIMES)
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
    parser.add_argument("--engines", nargs="+", default=["three-webgpu"], choices=["three-webgpu", "three"])
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
                for method in ("vbusd", "clones"):
                    result = run(browser, crowd, engine, method, args.frames)
                    label = {"three-webgpu": "three.js WebGPURenderer (WebGPU)", "three": "three.js WebGLRenderer"}[engine]
                    name = "vbusd (TSL)" if method == "vbusd" and engine == "three-webgpu" else (
                        "vbusd (GLSL)" if method == "vbusd" else "SkinnedMesh clones")
                    pose = f"{result['pose']:.2e}" if "pose" in result else "reference"
                    print(f"| {label} | {name} | {count:,} | {result['bytes']:,} | {result['cpu']:.1f} | "
                          f"{result['frame']:.1f} | {pose} |", flush=True)
                    if args.pictures:
                        args.pictures.mkdir(parents=True, exist_ok=True)
                        (args.pictures / f"side_by_side_{engine}_{method}_{count}.png").write_bytes(result["picture"])


if __name__ == "__main__":
    main()

// Test helpers: the packages the tests run on (built with `vbusd export`), the Khronos
// glTF-Validator, and skinned positions as the three.js runtime computes them under Node (three's
// GLTFLoader with the runtime's VirtualBonesGLTFPlugin, bone matrices from the runtime's
// boneRows: the texels decoded and blended between rows as the shader does).
import { execFileSync } from 'node:child_process';
import fs from 'node:fs';
import os from 'node:os';
import path from 'node:path';
import { fileURLToPath, pathToFileURL } from 'node:url';

import { NodeIO } from '@gltf-transform/core';
import { ALL_EXTENSIONS } from '@gltf-transform/extensions';
import draco3d from 'draco3dgltf';
import { MeshoptDecoder, MeshoptEncoder } from 'meshoptimizer';
import validator from 'gltf-validator';

import { VBUSDVirtualBones } from '../src/index.mjs';

export const HERE = path.dirname(fileURLToPath(import.meta.url));
export const REPO = path.resolve(HERE, '..', '..', '..');
const WEB = path.join(REPO, 'web');
const THREE = path.join(WEB, 'node_modules', 'three');

/** Why the three.js side cannot run here (web/ not installed), or null. */
export function threeMissing() {
  return fs.existsSync(path.join(THREE, 'package.json')) ? null : 'three.js not installed in web/ (scripts/install-node-deps.sh)';
}

let ioPromise = null;
/** A NodeIO with every Khronos extension, VBUSD_virtual_bones, and the Draco/meshopt codecs. */
export async function createIO() {
  ioPromise ??= (async () => {
    await MeshoptEncoder.ready;
    await MeshoptDecoder.ready;
    return new NodeIO()
      .registerExtensions([...ALL_EXTENSIONS, VBUSDVirtualBones])
      .registerDependencies({
        'draco3d.decoder': await draco3d.createDecoderModule(),
        'draco3d.encoder': await draco3d.createEncoderModule(),
        'meshopt.decoder': MeshoptDecoder,
        'meshopt.encoder': MeshoptEncoder,
      });
  })();
  return ioPromise;
}

function sharedAssets() {
  for (const candidate of [process.env.VBUSD_SHARED_ASSETS, path.resolve(REPO, '..', 'shared', 'assets')]) {
    if (candidate && fs.existsSync(path.join(candidate, 'gltf'))) return candidate;
  }
  return null;
}

let fixturesCache = null;
/**
 * The test packages: {name: path}: the stadium crowd sample (`crowd.glb`) and two glTF
 * characters (CesiumMan, Fox from the shared assets) converted and exported by vbusd. Taken from
 * $VBUSD_GLTF_TRANSFORM_FIXTURES when set (tests/test_gltf_transform.py builds them), else built
 * with $VBUSD_PYTHON (default python3) `-m vbusd`. Returns {packages, separate, missing: [reasons]},
 * `separate` the crowd as a .gltf with its .bin and .ktx2 beside it (gltf/crowd.gltf), or null.
 */
export function fixtures() {
  if (fixturesCache) return fixturesCache;
  const missing = [];
  let folder = process.env.VBUSD_GLTF_TRANSFORM_FIXTURES;
  if (!folder) {
    folder = fs.mkdtempSync(path.join(os.tmpdir(), 'vbusd-gltf-transform-'));
    const python = process.env.VBUSD_PYTHON || 'python3';
    const vbusd = (...args) => execFileSync(python, ['-m', 'vbusd', ...args], { stdio: 'pipe', env: { ...process.env, PYTHONSAFEPATH: '1' } });
    try {
      vbusd('export', path.join(REPO, 'samples', 'stadium_crowd', 'stadium_crowd_vb.usda'), '-o', path.join(folder, 'crowd.glb'));
      vbusd('export', path.join(REPO, 'samples', 'stadium_crowd', 'stadium_crowd_vb.usda'), '-o', path.join(folder, 'gltf', 'crowd.gltf'));
      const assets = sharedAssets();
      if (!assets) missing.push('shared glTF characters not found (set VBUSD_SHARED_ASSETS)');
      for (const name of assets ? ['CesiumMan', 'Fox'] : []) {
        vbusd('convert', path.join(assets, 'gltf', name, `${name}.glb`), '-o', path.join(folder, name, `${name}.usda`));
        vbusd('export', path.join(folder, name, `${name}.usda`), '-o', path.join(folder, `${name}.glb`));
      }
    } catch (error) {
      missing.push(`vbusd could not build the packages with ${python} (set VBUSD_PYTHON): ${String(error.stderr ?? error.message).trim().split('\n').pop()}`);
    }
  }
  const packages = {};
  for (const name of ['crowd', 'CesiumMan', 'Fox']) {
    const file = path.join(folder, `${name}.glb`);
    if (fs.existsSync(file)) packages[name] = file;
  }
  const separate = path.join(folder, 'gltf', 'crowd.gltf');
  fixturesCache = { packages, separate: fs.existsSync(separate) ? separate : null, missing };
  return fixturesCache;
}

/** The glTF-Validator's report of a GLB (bytes). */
export async function validate(bytes) {
  return validator.validateBytes(new Uint8Array(bytes), { maxIssues: 100, writeTimestamp: false });
}

/** The validator's errors, as short strings (empty when none). */
export async function validatorErrors(bytes) {
  const report = await validate(bytes);
  return report.issues.messages.filter((m) => m.severity === 0).map((m) => `${m.code} ${m.pointer ?? ''}: ${m.message}`);
}

let threeModules = null;
async function three() {
  threeModules ??= {
    THREE: await import(pathToFileURL(path.join(THREE, 'build', 'three.module.js')).href),
    GLTFLoader: (await import(pathToFileURL(path.join(THREE, 'examples', 'jsm', 'loaders', 'GLTFLoader.js')).href)).GLTFLoader,
    MeshoptDecoder: (await import(pathToFileURL(path.join(THREE, 'examples', 'jsm', 'libs', 'meshopt_decoder.module.js')).href)).MeshoptDecoder,
    plugin: await import(pathToFileURL(path.join(WEB, 'src', 'gltf-plugin.js')).href),
    sockets: await import(pathToFileURL(path.join(WEB, 'src', 'sockets.js')).href),
  };
  return threeModules;
}

/** Loads a GLB (bytes) with three's GLTFLoader, the runtime plugin and the meshopt decoder. */
export async function loadThree(bytes) {
  const { GLTFLoader, MeshoptDecoder: decoder, plugin } = await three();
  globalThis.ProgressEvent ??= class ProgressEvent extends Event {
    constructor(type, init = {}) { super(type); Object.assign(this, init); }
  };
  const loader = new GLTFLoader().setMeshoptDecoder(decoder);
  loader.register((parser) => new plugin.VirtualBonesGLTFPlugin(parser));
  const buffer = bytes.buffer.slice(bytes.byteOffset, bytes.byteOffset + bytes.byteLength);
  return loader.parseAsync(buffer, '');
}

/**
 * Skinned world positions of a package, per animation name: for each drawing (crowd node or
 * character node) and each of its sampled instances (first, middle, last), each vertex the
 * indices reference, one point [x(t0), y(t0), z(t0), x(t1), ...] at the given scene times.
 * Returns {animationName: {points: Float64Array, stride, count, restDiagonal}}, restDiagonal the
 * bounding-box diagonal of the rest positions (mesh space: the character's size).
 */
export async function skinnedPoints(bytes, times) {
  const { THREE: T, sockets } = await three();
  const gltf = await loadThree(bytes);
  const { animations, crowds } = gltf.userData.virtualBones;
  const out = {};
  const stride = 3 * times.length;
  for (const crowd of crowds) {
    const { animation, meshes } = animations[crowd.animation];
    const name = animation.name;
    const rowsCache = new Map();
    const bone = (clip, tau, b) => {
      const key = `${clip}|${tau}|${b}`;
      if (!rowsCache.has(key)) rowsCache.set(key, sockets.boneRows(animation, clip, tau, b));
      return rowsCache.get(key);
    };
    const { instances } = crowd;
    const picks = [...new Set([0, Math.floor(instances.count / 2), instances.count - 1])];
    const values = [];
    const restMin = [Infinity, Infinity, Infinity];
    const restMax = [-Infinity, -Infinity, -Infinity];
    for (const i of picks) {
      const world = new T.Matrix4().copy(crowd.matrix).multiply(new T.Matrix4().fromArray(instances.matrices, 16 * i));
      const e = world.elements;
      for (const mesh of meshes) {
        const g = mesh.geometry;
        const position = g.attributes.position;
        const used = g.index ? [...new Set(Array.from({ length: g.index.count }, (_, k) => g.index.getX(k)))] : [...Array(position.count).keys()];
        const sets = Math.ceil(mesh.maxInfluences / 4);
        for (const v of used) {
          const p = [position.getX(v), position.getY(v), position.getZ(v)];
          for (let c = 0; c < 3; ++c) { restMin[c] = Math.min(restMin[c], p[c]); restMax[c] = Math.max(restMax[c], p[c]); }
          for (const t of times) {
            const tau = instances.timeOffset[i] + instances.playbackRate[i] * t;
            const s = [0, 0, 0];
            for (let k = 0; k < mesh.maxInfluences; ++k) {
              const set = k >> 2;
              if (set >= sets) break;
              const w = g.attributes[`vb_boneWeights${set}`].getComponent(v, k & 3);
              if (w === 0) continue;
              const rows = bone(instances.clip[i], tau, g.attributes[`vb_boneIndices${set}`].getComponent(v, k & 3));
              for (let r = 0; r < 3; ++r) s[r] += w * (rows[r][0] * p[0] + rows[r][1] * p[1] + rows[r][2] * p[2] + rows[r][3]);
            }
            values.push(e[0] * s[0] + e[4] * s[1] + e[8] * s[2] + e[12],
              e[1] * s[0] + e[5] * s[1] + e[9] * s[2] + e[13],
              e[2] * s[0] + e[6] * s[1] + e[10] * s[2] + e[14]);
          }
        }
      }
    }
    const previous = out[name]?.points ?? [];
    const points = Float64Array.from([...previous, ...values]);
    const restDiagonal = Math.max(out[name]?.restDiagonal ?? 0, Math.hypot(...restMax.map((m, c) => m - restMin[c])));
    out[name] = { points, stride, count: points.length / stride, restDiagonal };
  }
  return out;
}

/** Bounding-box diagonal of a point set's positions (all times together). */
export function diagonal({ points }) {
  const min = [Infinity, Infinity, Infinity];
  const max = [-Infinity, -Infinity, -Infinity];
  for (let i = 0; i < points.length; i += 3) {
    for (let c = 0; c < 3; ++c) { min[c] = Math.min(min[c], points[i + c]); max[c] = Math.max(max[c], points[i + c]); }
  }
  return Math.hypot(max[0] - min[0], max[1] - min[1], max[2] - min[2]);
}

function oneWay(a, b, stride, window) {
  // b sorted on its first coordinate; each point of a is matched with the point of b, among those
  // within `window` on that coordinate, whose farthest time is nearest.
  const order = Array.from({ length: b.length / stride }, (_, i) => i).sort((i, j) => b[i * stride] - b[j * stride]);
  const keys = Float64Array.from(order, (i) => b[i * stride]);
  let worst = 0;
  for (let i = 0; i < a.length / stride; ++i) {
    const x = a[i * stride];
    let lo = 0; let hi = keys.length;
    while (lo < hi) { const mid = (lo + hi) >> 1; if (keys[mid] < x - window) lo = mid + 1; else hi = mid; }
    let best = Infinity;
    for (let k = lo; k < keys.length && keys[k] <= x + window; ++k) {
      const j = order[k];
      let d = 0;
      for (let t = 0; t < stride; t += 3) {
        d = Math.max(d, Math.hypot(a[i * stride + t] - b[j * stride + t], a[i * stride + t + 1] - b[j * stride + t + 1], a[i * stride + t + 2] - b[j * stride + t + 2]));
      }
      best = Math.min(best, d);
    }
    worst = Math.max(worst, best);
  }
  return worst;
}

/**
 * Largest distance between matched skinned vertices of two packages' point sets (both ways:
 * every vertex before has one after within it, and every vertex after one before), so vertex
 * order, welding, joining and instancing do not matter. `window` bounds the search.
 */
export function skinDistance(before, after, window) {
  if (before.stride !== after.stride) throw new Error('different times');
  return Math.max(oneWay(before.points, after.points, before.stride, window), oneWay(after.points, before.points, before.stride, window));
}

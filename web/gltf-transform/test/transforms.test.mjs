// The standard glTF-Transform transforms on vbusd runtime packages (the stadium crowd and two
// glTF characters): each output passes the Khronos glTF-Validator with no error and, loaded in
// three.js with the runtime's GLTFLoader plugin, gives the same skinned positions as the input,
// within 1e-6 of the bounding-box diagonal (Draco: within its stated quantization bound).
// Run: `node --test test/` in web/gltf-transform (tests/test_gltf_transform.py runs it too).
import assert from 'node:assert/strict';
import fs from 'node:fs';
import { describe, test } from 'node:test';

import { EXTMeshoptCompression } from '@gltf-transform/extensions';
import {
  dedup, draco, flatten, instance, join, meshopt, prune, quantize, reorder, resample, weld,
} from '@gltf-transform/functions';
import { MeshoptEncoder } from 'meshoptimizer';

import {
  VBUSD_VIRTUAL_BONES, VirtualBonesError, vbusdInstanceDefaults, vbusdMeshopt, vbusdQuantize,
} from '../src/index.mjs';
import {
  createIO, diagonal, fixtures, skinDistance, skinnedPoints, threeMissing, validatorErrors,
} from './helpers.mjs';

const TIMES = [0, 0.37, 1.2345];  // a row time, between rows, further on
const TOLERANCE = 1e-6;  // of the bounding-box diagonal of the sampled skinned vertices
// Draco's defaults: POSITION on 14 bits, the skin weights (generic attributes) on 12 bits over
// each attribute's range. A vertex moves by at most 2^-14 of the mesh's extent, and each of its
// K = 4 weights by 2^-12, which moves the skinned point by at most 4 * 2^-12 of the bone-space
// offsets |M p| (below the diagonal here): together below 2^-9 of the diagonal.
const DRACO_TOLERANCE = 2 ** -9;

const { packages, missing } = fixtures();
const skip = threeMissing() ?? (Object.keys(packages).length ? false : missing.join('; ') || 'no packages');

/** [name, transforms to apply, options]. */
const TRANSFORMS = [
  ['dedup', () => [dedup()]],
  ['prune', () => [prune()]],
  ['weld', () => [weld()]],
  ['reorder', () => [reorder({ encoder: MeshoptEncoder })]],
  ['quantize (vbusdQuantize)', () => [vbusdQuantize()]],
  ['resample', () => [resample()]],
  ['flatten', () => [flatten()]],
  ['join', () => [join()]],
  ['join (keepMeshes: false)', () => [join({ keepMeshes: false, keepNamed: false })]],
  ['meshopt (vbusdMeshopt)', () => [vbusdMeshopt({ encoder: MeshoptEncoder, extension: EXTMeshoptCompression })]],
  ['meshopt medium (vbusdMeshopt)', () => [vbusdMeshopt({ encoder: MeshoptEncoder, extension: EXTMeshoptCompression, level: 'medium' })]],
  ['draco', () => [draco()], { decode: true, tolerance: DRACO_TOLERANCE }],
  ['draco (lossless skin)', () => [draco({ quantizeGeneric: 0 })], { decode: true, tolerance: DRACO_TOLERANCE }],
];

async function roundTrip(io, bytes, transforms) {
  const document = await io.readBinary(new Uint8Array(bytes));
  await document.transform(...transforms);
  return io.writeBinary(document);
}

/** Draco output decoded with glTF-Transform's Draco decoder (three's DRACOLoader needs Workers). */
async function decoded(io, bytes) {
  const document = await io.readBinary(bytes);
  document.getRoot().listExtensionsUsed().find((e) => e.extensionName === 'KHR_draco_mesh_compression')?.dispose();
  return io.writeBinary(document);
}

async function compare(before, after, tolerance) {
  const a = await skinnedPoints(before, TIMES);
  const b = await skinnedPoints(after, TIMES);
  assert.deepEqual(Object.keys(b).sort(), Object.keys(a).sort());
  for (const name of Object.keys(a)) {
    const diag = diagonal(a[name]);
    const distance = skinDistance(a[name], b[name], tolerance * diag * 4);
    assert.ok(distance <= tolerance * diag, `${name}: skinned positions moved by ${distance} (${distance / diag} of the diagonal ${diag})`);
  }
}

describe('transforms keep Virtual Bones skinning', { skip }, () => {
  for (const [fixture, file] of Object.entries(packages)) {
    for (const [name, transforms, options = {}] of TRANSFORMS) {
      test(`${fixture}: ${name}`, async () => {
        const io = await createIO();
        const before = new Uint8Array(fs.readFileSync(file));
        const after = await roundTrip(io, before, transforms());
        assert.deepEqual(await validatorErrors(after), []);
        const json = (await io.binaryToJSON(after)).json;
        assert.ok(json.extensionsUsed.includes(VBUSD_VIRTUAL_BONES));
        assert.ok(!(json.extensionsRequired ?? []).includes(VBUSD_VIRTUAL_BONES));
        for (const { texture } of json.extensions[VBUSD_VIRTUAL_BONES].animations) {
          assert.equal(json.bufferViews[texture.bufferView].byteOffset % 16, 0, 'texture buffer view not 16-byte aligned');
        }
        await compare(before, options.decode ? await decoded(io, after) : after, options.tolerance ?? TOLERANCE);
      });
    }

    test(`${fixture}: instance() of repeated character nodes, completed by vbusdInstanceDefaults()`, async () => {
      const io = await createIO();
      // Two more plain nodes drawing the first animation's mesh, beside the package's own nodes.
      const document = await io.readBinary(new Uint8Array(fs.readFileSync(file)));
      const mesh = document.getRoot().listMeshes().find((m) => m.listPrimitives().some((p) => p.getExtension(VBUSD_VIRTUAL_BONES)));
      const scene = document.getRoot().listScenes()[0];
      for (const x of [3, -3]) scene.addChild(document.createNode(`copy${x}`).setMesh(mesh).setTranslation([x, 0, 1]));
      const before = await io.writeBinary(document);
      await assert.rejects(roundTrip(io, before, [instance({ min: 2 })]), (error) => error instanceof VirtualBonesError && /_VB_CLIP/.test(error.message));
      const after = await roundTrip(io, before, [instance({ min: 2 }), vbusdInstanceDefaults()]);
      const json = (await io.binaryToJSON(after)).json;
      assert.ok(json.nodes.some((n) => n.extensions?.EXT_mesh_gpu_instancing?.attributes?._VB_CLIP !== undefined && n.name !== 'Crowd'));
      assert.deepEqual(await validatorErrors(after), []);
      await compare(before, after, TOLERANCE);
    });

    test(`${fixture}: quantize() and meshopt() of POSITION are refused with a clear error`, async () => {
      const io = await createIO();
      const before = new Uint8Array(fs.readFileSync(file));
      for (const transforms of [[quantize()], [meshopt({ encoder: MeshoptEncoder })]]) {
        await assert.rejects(roundTrip(io, before, transforms),
          (error) => error instanceof VirtualBonesError && /POSITION is quantized/.test(error.message) && /vbusdQuantize/.test(error.message));
      }
    });
  }
});

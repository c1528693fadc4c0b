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
  dedup, draco, flatten, instance, join, mergeDocuments, meshopt, prune, quantize, reorder, resample, unpartition, weld,
} from '@gltf-transform/functions';
import { MeshoptEncoder } from 'meshoptimizer';

import {
  VBUSD_VIRTUAL_BONES, VirtualBonesError, vbusdInstanceDefaults, vbusdJoin, vbusdMeshopt, vbusdQuantize,
} from '../src/index.mjs';
import {
  createIO, diagonal, fixtures, skinDistance, skinnedPoints, threeMissing, validatorErrors,
} from './helpers.mjs';

const TIMES = [0, 0.37, 1.2345];  // a row time, between rows, further on
const TOLERANCE = 1e-6;  // of the bounding-box diagonal of the sampled skinned vertices
// Draco's defaults quantize inside the codec: POSITION on 14 bits over the mesh's largest extent
// E (each coordinate within half a step: |dp| <= sqrt(3) E / 2^15 = 5.3e-5 E) and the weights
// (generic attributes) on 12 bits over [0, 1] (each within 1 / 8190; the K = 4 weights move the
// skinned point by at most 4.9e-4 max|M p|, and |M p| stays below the character's size here).
// Together below 2^-10 of the character's rest diagonal (measured: 1.3e-4 at most, CesiumMan).
const DRACO_TOLERANCE = 2 ** -10;

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
  ['draco', () => [draco()], { decode: true, tolerance: DRACO_TOLERANCE, ofRest: true }],
  ['draco (weights not quantized)', () => [draco({ quantizeGeneric: 0 })], { decode: true, tolerance: DRACO_TOLERANCE, ofRest: true }],
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

async function compare(before, after, tolerance, ofRest = false) {
  const a = await skinnedPoints(before, TIMES);
  const b = await skinnedPoints(after, TIMES);
  assert.deepEqual(Object.keys(b).sort(), Object.keys(a).sort());
  for (const name of Object.keys(a)) {
    // The bounding box of the sampled skinned vertices (lossless transforms), or of the rest
    // mesh, the character's size (Draco's bound scales with it, not with the crowd's spread).
    const diag = ofRest ? a[name].restDiagonal : diagonal(a[name]);
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
        await compare(before, options.decode ? await decoded(io, after) : after, options.tolerance ?? TOLERANCE, options.ofRest);
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

    test(`${fixture}: the skinned-position check sees a broken skin (negative control)`, async () => {
      const io = await createIO();
      const before = new Uint8Array(fs.readFileSync(file));
      const document = await io.readBinary(before);
      // Every vertex bound to bone 0 only: the rest pose moved rigidly by one bone.
      for (const prim of document.getRoot().listMeshes().flatMap((m) => m.listPrimitives())) {
        for (const semantic of prim.listSemantics().filter((s) => s.startsWith('_VB_JOINTS_'))) {
          const joints = prim.getAttribute(semantic).clone();
          const Ctor = joints.getArray().constructor;
          joints.setArray(new Ctor(joints.getArray().length));
          prim.setAttribute(semantic, joints);
        }
      }
      await assert.rejects(compare(before, await io.writeBinary(document), TOLERANCE), /skinned positions moved/);
    });

    test(`${fixture}: join() across nodes is refused at write; vbusdJoin() keeps each character's skin`, async () => {
      const io = await createIO();
      // A second character node beside the first, moved: join({keepMeshes: false}) would move its
      // rest vertices into the first node's space, which skinning does not commute with.
      const document = await io.readBinary(new Uint8Array(fs.readFileSync(file)));
      const mesh = document.getRoot().listMeshes().find((m) => m.listPrimitives().some((p) => p.getExtension(VBUSD_VIRTUAL_BONES)));
      const parent = document.getRoot().listNodes().find((n) => n.getName() === 'vbusd');
      // Two of them, so that the crowd (whose instanced node join() skips) has a pair too.
      parent.addChild(document.createNode('moved').setMesh(mesh).setTranslation([2, 0, 1]));
      parent.addChild(document.createNode('moved2').setMesh(mesh).setTranslation([-2, 0, 1]));
      const before = await io.writeBinary(document);
      await assert.rejects(roundTrip(io, before, [join({ keepMeshes: false, keepNamed: false })]),
        (error) => error instanceof VirtualBonesError && /no VBUSD_virtual_bones binding/.test(error.message) && /vbusdJoin/.test(error.message));
      const after = await roundTrip(io, before, [vbusdJoin({ keepMeshes: false, keepNamed: false })]);
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

  test('merge (gltf-transform merge) of the crowd and a character keeps both animations', { skip: packages.crowd && packages.Fox ? false : 'needs crowd and Fox' }, async () => {
    const io = await createIO();
    const merged = await io.read(packages.crowd);
    mergeDocuments(merged, await io.read(packages.Fox));
    await merged.transform(unpartition());
    const after = await io.writeBinary(merged);
    assert.deepEqual(await validatorErrors(after), []);
    const skinnedAfter = await skinnedPoints(after, TIMES);
    for (const name of ['crowd', 'Fox']) {
      const before = await skinnedPoints(new Uint8Array(fs.readFileSync(packages[name])), TIMES);
      for (const [animation, points] of Object.entries(before)) {
        const distance = skinDistance(points, skinnedAfter[animation], TOLERANCE * diagonal(points) * 4);
        assert.ok(distance <= TOLERANCE * diagonal(points), `${animation}: moved by ${distance}`);
      }
    }
  });
});

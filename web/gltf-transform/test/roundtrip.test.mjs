// Reading and writing VBUSD_virtual_bones: a package read with the extension and written back
// holds the same extension objects (the texture's bytes identical to the KTX2 file vbusd wrote,
// compared with the input's own buffer view), and writing is a fixed point; documents the
// extension cannot keep working are refused with one clear error.
import assert from 'node:assert/strict';
import fs from 'node:fs';
import { describe, test } from 'node:test';

import os from 'node:os';
import path from 'node:path';

import { NodeIO } from '@gltf-transform/core';
import { unpartition, weld } from '@gltf-transform/functions';

import { VBUSD_VIRTUAL_BONES, VBUSDVirtualBones, VirtualBonesError } from '../src/index.mjs';
import { createIO, fixtures } from './helpers.mjs';

const { packages, separate, missing } = fixtures();
const skip = Object.keys(packages).length ? false : missing.join('; ') || 'no packages';

/** {json, bin} of a GLB, parsed here (not by glTF-Transform). */
function parseGLB(bytes) {
  const view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  const jsonLength = view.getUint32(12, true);
  const json = JSON.parse(new TextDecoder().decode(bytes.subarray(20, 20 + jsonLength)));
  const binStart = 20 + jsonLength + 8;
  return { json, bin: bytes.subarray(binStart, binStart + view.getUint32(20 + jsonLength, true)) };
}

function textureBytes({ json, bin }, animation) {
  const view = json.bufferViews[animation.texture.bufferView];
  return bin.subarray(view.byteOffset ?? 0, (view.byteOffset ?? 0) + view.byteLength);
}

describe('VBUSD_virtual_bones round trip', { skip }, () => {
  for (const [fixture, file] of Object.entries(packages)) {
    test(`${fixture}: read and written back, the extension is equal`, async () => {
      const io = await createIO();
      const input = new Uint8Array(fs.readFileSync(file));
      const before = parseGLB(input);
      const output = await io.writeBinary(await io.readBinary(input));
      const after = parseGLB(output);
      const rootBefore = before.json.extensions[VBUSD_VIRTUAL_BONES];
      const rootAfter = after.json.extensions[VBUSD_VIRTUAL_BONES];
      assert.equal(rootAfter.version, 1);
      assert.equal(rootAfter.animations.length, rootBefore.animations.length);
      rootBefore.animations.forEach((animation, a) => {
        const { texture, ...rest } = animation;
        const { texture: textureAfter, ...restAfter } = rootAfter.animations[a];
        // As JSON values: JSON.stringify writes -0 (which vbusd's Python writer keeps as -0.0 in a
        // clip extent) as 0, and JSON numbers compare equal either way.
        assert.deepEqual(restAfter, JSON.parse(JSON.stringify(rest)));
        assert.equal(textureAfter.mimeType, 'image/ktx2');
        assert.deepEqual(textureBytes(after, rootAfter.animations[a]), textureBytes(before, animation));
        const viewAfter = after.json.bufferViews[textureAfter.bufferView];
        assert.equal(viewAfter.byteOffset % 16, 0);
        assert.equal(viewAfter.byteStride, undefined);
        assert.equal(viewAfter.target, undefined);
      });
      // The typed view agrees with the file: clips from the layout, bindings to their animations.
      const document = await io.readBinary(input);
      const extension = document.getRoot().listExtensionsUsed().find((e) => e.extensionName === VBUSD_VIRTUAL_BONES);
      const typed = extension.listAnimations();
      assert.deepEqual(typed.map((a) => a.getName()), rootBefore.animations.map((a) => a.name));
      assert.deepEqual(typed.map((a) => a.listClips().map((c) => c.name)), rootBefore.animations.map((a) => a.layout.clips.map((c) => c.name)));
      for (const [m, mesh] of document.getRoot().listMeshes().entries()) {
        for (const [p, prim] of mesh.listPrimitives().entries()) {
          const def = before.json.meshes[m].primitives[p].extensions?.[VBUSD_VIRTUAL_BONES];
          const binding = prim.getExtension(VBUSD_VIRTUAL_BONES);
          assert.equal(binding ? typed.indexOf(binding.getAnimation()) : undefined, def?.animation);
          assert.equal(binding?.getInfluences(), def?.influences);
        }
      }
      const bindings = (json) => json.meshes.flatMap((m) => m.primitives.map((p) => p.extensions?.[VBUSD_VIRTUAL_BONES] ?? null));
      assert.deepEqual(bindings(after.json), bindings(before.json));
      assert.ok(after.json.extensionsUsed.includes(VBUSD_VIRTUAL_BONES));
      assert.ok(!(after.json.extensionsRequired ?? []).includes(VBUSD_VIRTUAL_BONES));
      // A second pass changes nothing: the written form is a fixed point.
      const again = await io.writeBinary(await io.readBinary(output));
      assert.deepEqual(again, output);
    });

    test(`${fixture}: without the extension registered, glTF-Transform drops it (why it is needed)`, async () => {
      const plain = new NodeIO();
      const output = parseGLB(await plain.writeBinary(await plain.readBinary(new Uint8Array(fs.readFileSync(file)))));
      assert.equal(output.json.extensions?.[VBUSD_VIRTUAL_BONES], undefined);
    });

    test(`${fixture}: a lost skin attribute is refused at write, naming the mesh`, async () => {
      const io = await createIO();
      const document = await io.readBinary(new Uint8Array(fs.readFileSync(file)));
      const mesh = document.getRoot().listMeshes().find((m) => m.listPrimitives()[0].getExtension(VBUSD_VIRTUAL_BONES));
      mesh.listPrimitives()[0].setAttribute('_VB_WEIGHTS_0', null);
      await assert.rejects(io.writeBinary(document), (error) => error instanceof VirtualBonesError
        && error.message.includes(`mesh "${mesh.getName()}" primitive 0`) && /_VB_WEIGHTS_0/.test(error.message));
    });
  }

  test('a .gltf package: written back as .gltf the KTX2 stays its own file, byte for byte; unpartition() makes a GLB', { skip: separate ? false : 'no .gltf package' }, async () => {
    const io = await createIO();
    const out = fs.mkdtempSync(path.join(os.tmpdir(), 'vbusd-gltf-transform-'));
    const document = await io.read(separate);
    await document.transform(weld());
    await io.write(path.join(out, 'crowd.gltf'), document);
    const json = JSON.parse(fs.readFileSync(path.join(out, 'crowd.gltf'), 'utf8'));
    const [animation] = json.extensions[VBUSD_VIRTUAL_BONES].animations;
    const view = json.bufferViews[animation.texture.bufferView];
    const uri = json.buffers[view.buffer].uri;
    assert.equal(uri, 'crowd.Cheer.ktx2');
    assert.equal(view.byteOffset ?? 0, 0);
    assert.deepEqual(fs.readFileSync(path.join(out, uri)), fs.readFileSync(path.join(path.dirname(separate), uri)));
    // GLB holds one buffer: unpartition() (the CLI does it for a .glb output) moves the texture too.
    await assert.rejects(io.writeBinary(await io.read(separate)), /GLB must have 0–1 buffers/);
    const merged = await io.read(separate);
    await merged.transform(unpartition());
    const glb = parseGLB(await io.writeBinary(merged));
    const [moved] = glb.json.extensions[VBUSD_VIRTUAL_BONES].animations;
    assert.deepEqual(Buffer.from(textureBytes(glb, moved)), fs.readFileSync(path.join(path.dirname(separate), uri)));
    assert.equal(glb.json.bufferViews[moved.texture.bufferView].byteOffset % 16, 0);
  });

  test('an unknown extension version is refused with one clear line', async () => {
    const io = await createIO();
    const [file] = Object.values(packages);
    const jsonDoc = await io.binaryToJSON(new Uint8Array(fs.readFileSync(file)));
    jsonDoc.json.extensions[VBUSD_VIRTUAL_BONES].version = 2;
    await assert.rejects(io.readJSON(jsonDoc), (error) => error instanceof VirtualBonesError
      && /version 2 is not 1/.test(error.message) && !error.message.includes('\n'));
  });

  test('the extension class is registered under its name', () => {
    assert.equal(VBUSDVirtualBones.EXTENSION_NAME, VBUSD_VIRTUAL_BONES);
  });
});

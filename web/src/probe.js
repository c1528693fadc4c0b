// The GPU's own skinned vertices, read back for tests: transform feedback in WebGL 2 through
// three's context, with the same GLSL (module + skinning call) that the patched materials run and
// the instance data of the crowd's own attribute arrays.

import {
  VirtualBonesError, DEFAULT_FRAME_INTERVAL, probeProgram, probeOutputs, runFeedback, assetOrder, concatenate,
} from '@vbusd/core';

import { previousDeclarations, previousSkinningCall, skinningCall, skinningDeclarations } from './material.js';
import { DEFAULT_SKIN } from './skin.js';

function vertexSource(animation, maxInfluences, skin, layers, previous) {
  return `#version 300 es
precision highp float;
precision highp int;
${skinningDeclarations(animation, maxInfluences, skin, layers)}
${previousDeclarations()}
in vec3 position;
in vec3 normal;
in mat4 instanceMatrix;
uniform mat4 modelMatrix;
out vec3 vbWorldPosition;
out vec3 vbWorldNormal;
${previous ? 'out vec3 vbWorldPreviousPosition;' : ''}
void main() {
${skinningCall(skin, layers)}
${previous ? previousSkinningCall(layers) : ''}
${probeOutputs('modelMatrix * instanceMatrix', { previous })}
}
`;
}

const vec4s = (vectors) => { const a = new Float32Array(4 * vectors.length); vectors.forEach((v, i) => v.toArray(a, 4 * i)); return a; };

/**
 * World-space skinned positions and normals of instance `index` of `crowd` at scene time `time`,
 * computed by the GPU: `{positions, normals, lod}` (Float32Arrays, and the level of detail the
 * instance was drawn with at the crowd's last updateLevels, whose meshes are skinned), each mesh of the animation in
 * order, points in the asset's order (normals in the asset's normal order: per point, or per
 * face-vertex for face-varying normals; empty for meshes without normals). The crowd's own skin
 * binding is used: with `pulled`, the skin records are read from the geometry's skin texture by
 * gl_VertexID, as the crowd's materials read them. `previousPositions` are the instance's
 * previous-frame pose for frame interval `dt` (spec 21; the velocity materials' vertex code:
 * material.js previousSkinningCall), in the order of `positions`; with `previous: false` none
 * (empty): the probe's shader then skins once, half the compile (seconds in software WebGL).
 */
export function probeCrowd(renderer, crowd, index, time, { dt = DEFAULT_FRAME_INTERVAL, previous: withPrevious = true } = {}) {
  const gl = renderer.getContext();
  if (!(index >= 0 && index < crowd.capacity)) throw new VirtualBonesError(`instance ${index} is not in ${crowd.name} (${crowd.capacity} instances)`);
  const animation = crowd.animation;
  animation.checkSupport(renderer);
  renderer.initTexture(animation.texture);
  if (crowd.layered) renderer.initTexture(animation.rigTexture);  // before any raw binding: three binds on unit 0
  const webglTexture = renderer.properties.get(animation.texture).__webglTexture;
  if (!webglTexture) throw new VirtualBonesError('the animation texture was not uploaded');
  crowd.updateMatrixWorld(true);
  const positions = [];
  const normals = [];
  const previous = [];
  // Levels of detail: the meshes of the level the instance was drawn with (LOD 0 when culled).
  const lod = crowd.levelOf ? crowd.levelOf(index) : 0;
  crowd.updateSamples?.(time);  // a fade over stage time: the instances' fades at `time`
  crowd.updatePrevious(time, dt);  // the previous frame: fades at time - dt, vb_previousTime
  for (const mesh of crowd.meshesOfLevel ? crowd.meshesOfLevel(Math.max(lod, 0)) : crowd.meshes) {
    const { maxInfluences } = mesh.userData.virtualBones;
    const skin = crowd.skin ?? DEFAULT_SKIN;
    const layers = Boolean(crowd.layered);
    const key = `three/${animation.encoding}/${animation.texelFormat}/${maxInfluences}/${animation.maxClips}/${animation.maxBones}/${skin}/${layers}/${withPrevious}`;
    const program = probeProgram(gl, key, vertexSource(animation, maxInfluences, skin, layers, withPrevious),
      { previous: withPrevious });
    const geometry = mesh.geometry;
    const vertexCount = geometry.attributes.position.count;
    let skinTexture = null;
    if (skin === 'pulled') {
      const records = geometry.userData.virtualBones.skin?.texture;
      if (!records) throw new VirtualBonesError(`${geometry.name}: the pulled skin has no texture`);
      renderer.initTexture(records);
      skinTexture = renderer.properties.get(records).__webglTexture;
      if (!skinTexture) throw new VirtualBonesError(`${geometry.name}: the skin texture was not uploaded`);
    }
    const results = runFeedback(gl, program, vertexCount, (input) => {
      input.attribute('position', geometry.attributes.position.array, 3);
      input.attribute('normal', geometry.attributes.normal.array, 3);
      for (const set of [0, 1]) {
        if (skin !== 'attributes' || !geometry.attributes[`vb_boneIndices${set}`]) continue;
        input.attribute(`vb_boneIndices${set}`, geometry.attributes[`vb_boneIndices${set}`].array, 4, { integer: true });
        input.attribute(`vb_boneWeights${set}`, geometry.attributes[`vb_boneWeights${set}`].array, 4);
      }
      // The instance's own entries of the crowd's arrays: divisor 1, offset at instance `index`.
      input.attribute('vb_instanceClip', crowd.clipAttribute.array, 1, { integer: true, divisor: 1, offset: 4 * index });
      input.attribute('vb_instanceTime', crowd.timeAttribute.array, 2, { divisor: 1, offset: 8 * index });
      input.attribute('vb_instanceFadeClip', crowd.fadeClipAttribute.array, 1, { integer: true, divisor: 1, offset: 4 * index });
      input.attribute('vb_instanceFade', crowd.fadeAttribute.array, 3, { divisor: 1, offset: 12 * index });
      input.attribute('vb_instancePreviousFade', crowd.previousFadeAttribute.array, 4, { divisor: 1, offset: 16 * index });
      input.attribute('instanceMatrix', crowd.instanceMatrix.array, 4, { divisor: 1, offset: 64 * index, columns: 4 });
      if (layers) {  // format 1.2: the instance's two layers
        input.attribute('vb_instanceLayerClipMask', crowd.layerClipMaskAttribute.array, 4, { integer: true, divisor: 1, offset: 16 * index });
        input.attribute('vb_instanceLayerTime', crowd.layerTimeAttribute.array, 4, { divisor: 1, offset: 16 * index });
        input.attribute('vb_instanceLayerWeight', crowd.layerWeightAttribute.array, 4, { divisor: 1, offset: 16 * index });
      }
      gl.activeTexture(gl.TEXTURE0);
      gl.bindTexture(gl.TEXTURE_2D, webglTexture);
      gl.uniform1i(input.uniform('vb_texture'), 0);
      if (skinTexture) {
        gl.activeTexture(gl.TEXTURE1);
        gl.bindTexture(gl.TEXTURE_2D, skinTexture);
        gl.uniform1i(input.uniform('vb_skinTexture'), 1);
      }
      if (layers) {
        gl.activeTexture(gl.TEXTURE2);
        gl.bindTexture(gl.TEXTURE_2D, renderer.properties.get(animation.rigTexture).__webglTexture);
        gl.uniform1i(input.uniform('vb_rig'), 2);
      }
      gl.uniform1f(input.uniform('vb_time'), time);
      gl.uniform1f(input.uniform('vb_previousTime'), animation.previousTime);
      gl.uniform4fv(input.uniform('vb_clips'), vec4s(animation.uniforms.vb_clips.value));
      if (animation.uniforms.vb_rangeMin) {
        gl.uniform4fv(input.uniform('vb_rangeMin'), vec4s(animation.uniforms.vb_rangeMin.value));
        gl.uniform4fv(input.uniform('vb_rangeMax'), vec4s(animation.uniforms.vb_rangeMax.value));
      }
      if (animation.uniforms.vb_compactRange) {  // format 1.2: per-bone ranges of the compact encoding
        gl.uniform4fv(input.uniform('vb_compactRange'), vec4s(animation.uniforms.vb_compactRange.value));
      }
      gl.uniformMatrix4fv(input.uniform('modelMatrix'), false, mesh.matrixWorld.elements);
    });
    const [points, normalsOfMesh, previousOfMesh] = assetOrder(results, geometry.userData.virtualBones);
    positions.push(points);
    normals.push(normalsOfMesh);
    previous.push(previousOfMesh);
  }
  renderer.resetState();  // three caches GL state; it must not trust it after raw calls
  return { positions: concatenate(positions), normals: concatenate(normals), previousPositions: concatenate(previous), lod };
}

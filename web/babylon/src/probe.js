// The GPU's own skinned vertices under Babylon.js, read back for tests. Babylon exposes no
// transform feedback, so the probe runs @vbusd/core's WebGL 2 transform-feedback pass on Babylon's
// own context (engine._gl) with the same GLSL the material plugin injects (skinning.js: module +
// skinning call), the mesh's own vertex data (or skin records), the animation's own uploaded
// textures, and one instance's playback as constant vertex attributes; then Babylon's GL state
// cache is wiped.

import {
  VirtualBonesError, DEFAULT_FRAME_INTERVAL, probeProgram, probeOutputs, runFeedback, assetOrder, concatenate,
} from '@vbusd/core';

import { previousSkinningCall, skinningCall, skinningDeclarations } from './skinning.js';

function vertexSource(animation, maxInfluences, skin, layers, previous) {
  return `#version 300 es
precision highp float;
precision highp int;
${skinningDeclarations(animation, maxInfluences, 'in', skin, layers)}
in vec3 position;
in vec3 normal;
uniform mat4 vb_world;
out vec3 vbWorldPosition;
out vec3 vbWorldNormal;
${previous ? 'out vec3 vbWorldPreviousPosition;' : ''}
void main() {
${skinningCall('position', 'normal', maxInfluences, skin, layers)}
${previous ? `  vec3 vbPreviousPosition;
${previousSkinningCall('position', 'normal', 'vbPreviousPosition', layers)}` : ''}
${probeOutputs('vb_world', { previous })}
}
`;
}

const glTexture = (texture) => texture?.getInternalTexture()?._hardwareTexture?.underlyingResource;

/**
 * World-space skinned positions and normals of instance `index` of `crowd` at scene time `time`,
 * computed by the GPU: `{positions, normals, lod}` (Float32Arrays, and the level of detail the
 * instance was drawn with at the crowd's last updateLevels, whose meshes are skinned), meshes in order, points
 * in the asset's order (normals empty for meshes without), as three.js' probeCrowd gives them;
 * `previousPositions` for frame interval `dt` unless `previous: false` (then the shader skins once).
 */
export function probeBabylonCrowd(engine, crowd, index, time, { dt = DEFAULT_FRAME_INTERVAL, previous: withPrevious = true } = {}) {
  const gl = engine._gl;
  if (!gl || typeof gl.beginTransformFeedback !== 'function') throw new VirtualBonesError('the probe needs a WebGL 2 engine');
  if (!(index >= 0 && index < crowd.capacity)) throw new VirtualBonesError(`instance ${index} is not in ${crowd.name} (${crowd.capacity} instances)`);
  const animation = crowd.animation;
  const texture = glTexture(animation.texture);
  if (!texture) throw new VirtualBonesError('the animation texture was not uploaded');
  crowd.updateSamples?.(time);  // a fade over stage time: the instances' fades at `time`
  crowd.updatePrevious(time, dt);  // the previous frame: fades at time - dt, vb_previousTime
  const skin = crowd.skin ?? 'attributes';
  const layers = Boolean(crowd.layered);
  const positions = [];
  const normals = [];
  const previous = [];
  // Levels of detail: the meshes of the level the instance was drawn with (LOD 0 when culled).
  const lod = crowd.levelOf ? crowd.levelOf(index) : 0;
  for (const mesh of crowd.meshesOfLevel ? crowd.meshesOfLevel(Math.max(lod, 0)) : crowd.meshes) {
    const info = mesh.metadata.virtualBones;
    const { maxInfluences } = info;
    const key = `babylon/${animation.encoding}/${animation.texelFormat}/${maxInfluences}/${animation.maxClips}/${animation.maxBones}/${skin}/${layers}/${withPrevious}`;
    const program = probeProgram(gl, key, vertexSource(animation, maxInfluences, skin, layers, withPrevious),
      { previous: withPrevious });
    const vertexCount = mesh.getTotalVertices();
    const results = runFeedback(gl, program, vertexCount, (input) => {
      input.attribute('position', Float32Array.from(mesh.getVerticesData('position')), 3);
      const restNormals = mesh.getVerticesData('normal');
      // A mesh without normals (a glTF primitive without NORMAL): any normal; the probe reports none.
      if (restNormals) input.attribute('normal', Float32Array.from(restNormals), 3);
      else input.constant('normal', [0, 0, 1]);
      if (skin === 'attributes') {
        info.sets.forEach(([indices, weights], set) => {
          input.attribute(`vb_boneIndices${set}`, indices, 4);
          input.attribute(`vb_boneWeights${set}`, weights, 4);
        });
      }
      // The instance's own thin-instance entries, as constant attributes.
      const streams = [['vb_instanceA', crowd.instanceA], ['vb_instanceB', crowd.instanceB]];
      if (layers) streams.push(['vb_instanceC', crowd.instanceC], ['vb_instanceD', crowd.instanceD], ['vb_instanceE', crowd.instanceE]);
      streams.push(['vb_instancePreviousFade', crowd.previous.values]);
      for (const [name, array] of streams) input.constant(name, array.subarray(4 * index, 4 * index + 4));
      const textures = [['vb_texture', texture]];
      if (skin === 'pulled') textures.push(['vb_skinTexture', glTexture(info.skinTexture)]);
      if (layers) textures.push(['vb_rig', glTexture(animation.rigTexture)]);
      textures.forEach(([name, handle], unit) => {
        if (!handle) throw new VirtualBonesError(`${mesh.name}: ${name} was not uploaded`);
        gl.activeTexture(gl.TEXTURE0 + unit);
        gl.bindTexture(gl.TEXTURE_2D, handle);
        gl.uniform1i(input.uniform(name), unit);
      });
      gl.uniform1f(input.uniform('vb_time'), time);
      gl.uniform1f(input.uniform('vb_previousTime'), animation.previousTime);
      gl.uniform4fv(input.uniform('vb_clips'), animation.clipTable);
      if (animation.ranges) {
        gl.uniform4fv(input.uniform('vb_rangeMin'), animation.ranges.min);
        gl.uniform4fv(input.uniform('vb_rangeMax'), animation.ranges.max);
      }
      if (animation.compactRanges) gl.uniform4fv(input.uniform('vb_compactRange'), animation.compactRanges);
      // Babylon's row-vector world: instance placement, then the mesh's world matrix.
      const world = crowd.instanceMatrix(index).multiply(mesh.computeWorldMatrix(true));
      gl.uniformMatrix4fv(input.uniform('vb_world'), false, world.toArray());
    });
    const [points, normalsOfMesh, previousOfMesh] = assetOrder(results, info);
    positions.push(points);
    normals.push(normalsOfMesh);
    previous.push(previousOfMesh);
  }
  engine.wipeCaches(true);  // Babylon caches GL state; it must not trust it after raw calls
  return { positions: concatenate(positions), normals: concatenate(normals), previousPositions: concatenate(previous), lod };
}

// The GPU's own skinned vertices, read back for tests: transform feedback in WebGL 2 through
// three's context, with the same GLSL (module + skinning call) that the patched materials run and
// the instance data of the crowd's own attribute arrays.

import { VirtualBonesError } from './animation.js';
import { skinningCall, skinningDeclarations } from './material.js';
import { DEFAULT_SKIN } from './skin.js';

const FRAGMENT = `#version 300 es
precision highp float;
out vec4 vbColor;
void main() { vbColor = vec4(0.0); }
`;

function vertexSource(animation, maxInfluences, skin, layers) {
  return `#version 300 es
precision highp float;
precision highp int;
${skinningDeclarations(animation, maxInfluences, skin, layers)}
in vec3 position;
in vec3 normal;
in mat4 instanceMatrix;
uniform mat4 modelMatrix;
out vec3 vbWorldPosition;
out vec3 vbWorldNormal;
void main() {
${skinningCall(skin, layers)}
  mat4 world = modelMatrix * instanceMatrix;
  vbWorldPosition = (world * vec4(vbPosition, 1.0)).xyz;
  vec3 n = transpose(inverse(mat3(world))) * vbNormal;
  float len = length(n);
  vbWorldNormal = len > 0.0 ? n / len : n;
  gl_Position = vec4(0.0, 0.0, 0.0, 1.0);
}
`;
}

function compile(gl, type, source) {
  const shader = gl.createShader(type);
  gl.shaderSource(shader, source);
  gl.compileShader(shader);
  if (!gl.getShaderParameter(shader, gl.COMPILE_STATUS)) {
    const log = gl.getShaderInfoLog(shader);
    gl.deleteShader(shader);
    throw new VirtualBonesError(`probe shader does not compile: ${log}`);
  }
  return shader;
}

const programs = new WeakMap();

function probeProgram(gl, animation, maxInfluences, skin, layers) {
  let cache = programs.get(gl);
  if (!cache) programs.set(gl, cache = new Map());
  const key = `${animation.encoding}/${animation.texelFormat}/${maxInfluences}/${animation.maxClips}/${skin}/${layers}`;
  if (cache.has(key)) return cache.get(key);
  const program = gl.createProgram();
  gl.attachShader(program, compile(gl, gl.VERTEX_SHADER, vertexSource(animation, maxInfluences, skin, layers)));
  gl.attachShader(program, compile(gl, gl.FRAGMENT_SHADER, FRAGMENT));
  gl.transformFeedbackVaryings(program, ['vbWorldPosition', 'vbWorldNormal'], gl.SEPARATE_ATTRIBS);
  gl.linkProgram(program);
  if (!gl.getProgramParameter(program, gl.LINK_STATUS)) throw new VirtualBonesError(`probe program does not link: ${gl.getProgramInfoLog(program)}`);
  cache.set(key, program);
  return program;
}

function bindAttribute(gl, program, name, data, size, { integer = false, divisor = 0, offset = 0, columns = 1 } = {}) {
  const location = gl.getAttribLocation(program, name);
  if (location < 0) return null;  // optimized out (e.g. normals unused)
  const buffer = gl.createBuffer();
  gl.bindBuffer(gl.ARRAY_BUFFER, buffer);
  gl.bufferData(gl.ARRAY_BUFFER, data, gl.STATIC_DRAW);
  const bytes = data.BYTES_PER_ELEMENT;
  for (let c = 0; c < columns; ++c) {
    gl.enableVertexAttribArray(location + c);
    if (integer) gl.vertexAttribIPointer(location + c, size, data instanceof Int16Array ? gl.SHORT : gl.INT, 0, offset);
    else gl.vertexAttribPointer(location + c, size, gl.FLOAT, false, size * columns * bytes, offset + c * size * bytes);
    gl.vertexAttribDivisor(location + c, divisor);
  }
  return buffer;
}

/**
 * World-space skinned positions and normals of instance `index` of `crowd` at scene time `time`,
 * computed by the GPU: `{positions, normals, lod}` (Float32Arrays, and the level of detail the
 * instance was drawn with at the crowd's last updateLevels, whose meshes are skinned), each mesh of the animation in
 * order, points in the asset's order (normals in the asset's normal order: per point, or per
 * face-vertex for face-varying normals; empty for meshes without normals). The crowd's own skin
 * binding is used: with `pulled`, the skin records are read from the geometry's skin texture by
 * gl_VertexID, as the crowd's materials read them.
 */
export function probeCrowd(renderer, crowd, index, time) {
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
  // Levels of detail: the meshes of the level the instance was drawn with (LOD 0 when culled).
  const lod = crowd.levelOf ? crowd.levelOf(index) : 0;
  for (const mesh of crowd.meshesOfLevel ? crowd.meshesOfLevel(Math.max(lod, 0)) : crowd.meshes) {
    const { maxInfluences } = mesh.userData.virtualBones;
    const skin = crowd.skin ?? DEFAULT_SKIN;
    const layers = Boolean(crowd.layered);
    const program = probeProgram(gl, animation, maxInfluences, skin, layers);
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
    const vao = gl.createVertexArray();
    gl.bindVertexArray(vao);
    const buffers = [
      bindAttribute(gl, program, 'position', geometry.attributes.position.array, 3),
      bindAttribute(gl, program, 'normal', geometry.attributes.normal.array, 3),
    ];
    if (skin === 'attributes') {
      buffers.push(bindAttribute(gl, program, 'vb_boneIndices0', geometry.attributes.vb_boneIndices0.array, 4, { integer: true }));
      buffers.push(bindAttribute(gl, program, 'vb_boneWeights0', geometry.attributes.vb_boneWeights0.array, 4));
    }
    if (skin === 'attributes' && geometry.attributes.vb_boneIndices1) {
      buffers.push(bindAttribute(gl, program, 'vb_boneIndices1', geometry.attributes.vb_boneIndices1.array, 4, { integer: true }));
      buffers.push(bindAttribute(gl, program, 'vb_boneWeights1', geometry.attributes.vb_boneWeights1.array, 4));
    }
    // The instance's own entries of the crowd's arrays: divisor 1, offset at instance `index`.
    buffers.push(bindAttribute(gl, program, 'vb_instanceClip', crowd.clipAttribute.array, 1, { integer: true, divisor: 1, offset: 4 * index }));
    buffers.push(bindAttribute(gl, program, 'vb_instanceTime', crowd.timeAttribute.array, 2, { divisor: 1, offset: 8 * index }));
    buffers.push(bindAttribute(gl, program, 'vb_instanceFadeClip', crowd.fadeClipAttribute.array, 1, { integer: true, divisor: 1, offset: 4 * index }));
    buffers.push(bindAttribute(gl, program, 'vb_instanceFade', crowd.fadeAttribute.array, 3, { divisor: 1, offset: 12 * index }));
    buffers.push(bindAttribute(gl, program, 'instanceMatrix', crowd.instanceMatrix.array, 4, { divisor: 1, offset: 64 * index, columns: 4 }));
    if (layers) {  // format 1.2: the instance's two layers
      buffers.push(bindAttribute(gl, program, 'vb_instanceLayerClipMask', crowd.layerClipMaskAttribute.array, 4, { integer: true, divisor: 1, offset: 16 * index }));
      buffers.push(bindAttribute(gl, program, 'vb_instanceLayerTime', crowd.layerTimeAttribute.array, 4, { divisor: 1, offset: 16 * index }));
      buffers.push(bindAttribute(gl, program, 'vb_instanceLayerWeight', crowd.layerWeightAttribute.array, 2, { divisor: 1, offset: 8 * index }));
    }

    gl.useProgram(program);
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D, webglTexture);
    gl.uniform1i(gl.getUniformLocation(program, 'vb_texture'), 0);
    if (skinTexture) {
      gl.activeTexture(gl.TEXTURE1);
      gl.bindTexture(gl.TEXTURE_2D, skinTexture);
      gl.uniform1i(gl.getUniformLocation(program, 'vb_skinTexture'), 1);
    }
    if (layers) {
      gl.activeTexture(gl.TEXTURE2);
      gl.bindTexture(gl.TEXTURE_2D, renderer.properties.get(animation.rigTexture).__webglTexture);
      gl.uniform1i(gl.getUniformLocation(program, 'vb_rig'), 2);
    }
    gl.uniform1f(gl.getUniformLocation(program, 'vb_time'), time);
    const clips = new Float32Array(4 * animation.maxClips);
    animation.uniforms.vb_clips.value.forEach((v, i) => v.toArray(clips, 4 * i));
    gl.uniform4fv(gl.getUniformLocation(program, 'vb_clips'), clips);
    if (animation.uniforms.vb_rangeMin) {
      const flat = (vectors) => { const a = new Float32Array(4 * vectors.length); vectors.forEach((v, i) => v.toArray(a, 4 * i)); return a; };
      gl.uniform4fv(gl.getUniformLocation(program, 'vb_rangeMin'), flat(animation.uniforms.vb_rangeMin.value));
      gl.uniform4fv(gl.getUniformLocation(program, 'vb_rangeMax'), flat(animation.uniforms.vb_rangeMax.value));
    }
    if (animation.uniforms.vb_compactRange) {  // format 1.2: per-bone ranges of the compact encoding
      const ranges = animation.uniforms.vb_compactRange.value;
      const a = new Float32Array(4 * ranges.length);
      ranges.forEach((v, i) => v.toArray(a, 4 * i));
      gl.uniform4fv(gl.getUniformLocation(program, 'vb_compactRange'), a);
    }
    gl.uniformMatrix4fv(gl.getUniformLocation(program, 'modelMatrix'), false, mesh.matrixWorld.elements);

    const outputs = [gl.createBuffer(), gl.createBuffer()];
    const feedback = gl.createTransformFeedback();
    gl.bindTransformFeedback(gl.TRANSFORM_FEEDBACK, feedback);
    outputs.forEach((buffer, slot) => {
      gl.bindBuffer(gl.TRANSFORM_FEEDBACK_BUFFER, buffer);
      gl.bufferData(gl.TRANSFORM_FEEDBACK_BUFFER, vertexCount * 12, gl.STREAM_READ);
      gl.bindBufferBase(gl.TRANSFORM_FEEDBACK_BUFFER, slot, buffer);
    });
    gl.enable(gl.RASTERIZER_DISCARD);
    gl.beginTransformFeedback(gl.POINTS);
    gl.drawArraysInstanced(gl.POINTS, 0, vertexCount, 1);
    gl.endTransformFeedback();
    gl.disable(gl.RASTERIZER_DISCARD);
    const results = outputs.map((buffer) => {
      const data = new Float32Array(vertexCount * 3);
      gl.bindBuffer(gl.TRANSFORM_FEEDBACK_BUFFER, buffer);
      gl.getBufferSubData(gl.TRANSFORM_FEEDBACK_BUFFER, 0, data);
      return data;
    });
    gl.bindBufferBase(gl.TRANSFORM_FEEDBACK_BUFFER, 0, null);
    gl.bindBufferBase(gl.TRANSFORM_FEEDBACK_BUFFER, 1, null);
    gl.bindTransformFeedback(gl.TRANSFORM_FEEDBACK, null);
    gl.bindVertexArray(null);
    gl.deleteTransformFeedback(feedback);
    gl.deleteVertexArray(vao);
    for (const buffer of [...buffers, ...outputs]) if (buffer) gl.deleteBuffer(buffer);

    // Back to the asset's order: vertex j of an unwelded mesh is face-vertex j of point pointIndex[j].
    const { pointIndex, hasNormals, pointCount } = geometry.userData.virtualBones;
    if (pointIndex) {
      const points = new Float32Array(pointCount * 3);
      pointIndex.forEach((point, j) => points.set(results[0].subarray(3 * j, 3 * j + 3), 3 * point));
      positions.push(points);
    } else {
      positions.push(results[0]);
    }
    normals.push(hasNormals ? results[1] : new Float32Array(0));
  }
  renderer.resetState();  // three caches GL state; it must not trust it after raw calls
  const concat = (arrays) => {
    const out = new Float32Array(arrays.reduce((n, a) => n + a.length, 0));
    let at = 0;
    for (const a of arrays) { out.set(a, at); at += a.length; }
    return out;
  };
  return { positions: concat(positions), normals: concat(normals), lod };
}

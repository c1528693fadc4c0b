// The GPU's own skinned vertices under Babylon.js, read back for tests. Babylon exposes no
// transform feedback, so the probe runs a WebGL 2 transform-feedback pass on Babylon's own
// context (engine._gl) with the same GLSL the material plugin injects (skinning.js: module +
// skinning call), the mesh's own vertex buffers' data, the animation's own uploaded texture, and
// one instance's playback as constant vertex attributes; then Babylon's GL state cache is wiped.

import { VirtualBonesError, skinningCall, skinningDeclarations } from './skinning.js';

const FRAGMENT = `#version 300 es
precision highp float;
out vec4 vbColor;
void main() { vbColor = vec4(0.0); }
`;

function vertexSource(animation, maxInfluences) {
  return `#version 300 es
precision highp float;
precision highp int;
${skinningDeclarations(animation, maxInfluences, 'in')}
in vec3 position;
in vec3 normal;
uniform mat4 vb_world;
out vec3 vbWorldPosition;
out vec3 vbWorldNormal;
void main() {
${skinningCall('position', 'normal', maxInfluences)}
  vbWorldPosition = (vb_world * vec4(vbPosition, 1.0)).xyz;
  vec3 n = transpose(inverse(mat3(vb_world))) * vbNormal;
  float len = length(n);
  vbWorldNormal = len > 0.0 ? n / len : n;
  gl_Position = vec4(0.0, 0.0, 0.0, 1.0);
}
`;
}

const programs = new WeakMap();

function compile(gl, type, source) {
  const shader = gl.createShader(type);
  gl.shaderSource(shader, source);
  gl.compileShader(shader);
  if (!gl.getShaderParameter(shader, gl.COMPILE_STATUS)) throw new VirtualBonesError(`probe shader does not compile: ${gl.getShaderInfoLog(shader)}`);
  return shader;
}

function program(gl, animation, maxInfluences) {
  let cache = programs.get(gl);
  if (!cache) programs.set(gl, cache = new Map());
  const key = `${animation.encoding}/${animation.texelFormat}/${maxInfluences}/${animation.maxClips}`;
  if (!cache.has(key)) {
    const p = gl.createProgram();
    gl.attachShader(p, compile(gl, gl.VERTEX_SHADER, vertexSource(animation, maxInfluences)));
    gl.attachShader(p, compile(gl, gl.FRAGMENT_SHADER, FRAGMENT));
    gl.transformFeedbackVaryings(p, ['vbWorldPosition', 'vbWorldNormal'], gl.SEPARATE_ATTRIBS);
    gl.linkProgram(p);
    if (!gl.getProgramParameter(p, gl.LINK_STATUS)) throw new VirtualBonesError(`probe program does not link: ${gl.getProgramInfoLog(p)}`);
    cache.set(key, p);
  }
  return cache.get(key);
}

/**
 * World-space skinned positions and normals of instance `index` of `crowd` at scene time `time`,
 * computed by the GPU: `{positions, normals}` (Float32Arrays), meshes in order, points in the
 * asset's order (normals empty for meshes without), as three.js' probeCrowd gives them.
 */
export function probeBabylonCrowd(engine, crowd, index, time) {
  const gl = engine._gl;
  if (!gl || typeof gl.beginTransformFeedback !== 'function') throw new VirtualBonesError('the probe needs a WebGL 2 engine');
  if (!(index >= 0 && index < crowd.capacity)) throw new VirtualBonesError(`instance ${index} is not in ${crowd.name} (${crowd.capacity} instances)`);
  const texture = crowd.animation.texture.getInternalTexture()?._hardwareTexture?.underlyingResource;
  if (!texture) throw new VirtualBonesError('the animation texture was not uploaded');
  const positions = [];
  const normals = [];
  for (const mesh of crowd.meshes) {
    const { maxInfluences, pointIndex, hasNormals, pointCount } = mesh.metadata.virtualBones;
    const p = program(gl, crowd.animation, maxInfluences);
    const vertexCount = mesh.getTotalVertices();
    const vao = gl.createVertexArray();
    gl.bindVertexArray(vao);
    const buffers = [];
    const bind = (name, kind, size) => {
      const location = gl.getAttribLocation(p, name);
      if (location < 0) return;
      const buffer = gl.createBuffer();
      gl.bindBuffer(gl.ARRAY_BUFFER, buffer);
      gl.bufferData(gl.ARRAY_BUFFER, Float32Array.from(mesh.getVerticesData(kind)), gl.STATIC_DRAW);
      gl.enableVertexAttribArray(location);
      gl.vertexAttribPointer(location, size, gl.FLOAT, false, 0, 0);
      buffers.push(buffer);
    };
    bind('position', 'position', 3);
    bind('normal', 'normal', 3);
    for (let set = 0; set < (maxInfluences > 4 ? 2 : 1); ++set) {
      bind(`vb_boneIndices${set}`, `vb_boneIndices${set}`, 4);
      bind(`vb_boneWeights${set}`, `vb_boneWeights${set}`, 4);
    }
    // The instance's own thin-instance entries, as constant attributes.
    const constant = (name, array) => {
      const location = gl.getAttribLocation(p, name);
      if (location >= 0) gl.vertexAttrib4fv(location, array.subarray(4 * index, 4 * index + 4));
    };
    gl.useProgram(p);
    constant('vb_instanceA', crowd.instanceA);
    constant('vb_instanceB', crowd.instanceB);
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D, texture);
    gl.uniform1i(gl.getUniformLocation(p, 'vb_texture'), 0);
    gl.uniform1f(gl.getUniformLocation(p, 'vb_time'), time);
    gl.uniform4fv(gl.getUniformLocation(p, 'vb_clips'), crowd.animation.clipTable);
    // Babylon's row-vector world: instance placement, then the mesh's world matrix.
    const world = crowd.instanceMatrix(index).multiply(mesh.computeWorldMatrix(true));
    gl.uniformMatrix4fv(gl.getUniformLocation(p, 'vb_world'), false, world.toArray());
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
    gl.drawArrays(gl.POINTS, 0, vertexCount);
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
    for (const buffer of [...buffers, ...outputs]) gl.deleteBuffer(buffer);
    if (pointIndex) {
      const points = new Float32Array(pointCount * 3);
      pointIndex.forEach((point, j) => points.set(results[0].subarray(3 * j, 3 * j + 3), 3 * point));
      positions.push(points);
    } else {
      positions.push(results[0]);
    }
    normals.push(hasNormals ? results[1] : new Float32Array(0));
  }
  engine.wipeCaches(true);  // Babylon caches GL state; it must not trust it after raw calls
  const concat = (arrays) => {
    const out = new Float32Array(arrays.reduce((n, a) => n + a.length, 0));
    let at = 0;
    for (const a of arrays) { out.set(a, at); at += a.length; }
    return out;
  };
  return { positions: concat(positions), normals: concat(normals) };
}

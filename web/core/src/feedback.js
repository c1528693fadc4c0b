// The GPU's own skinned vertices, read back for tests and tools: a WebGL 2 transform-feedback pass
// on an engine's own context (three.js' WebGLRenderer, Babylon.js' Engine), with the vertex shader
// an engine's materials run (module + skinning call) writing world-space vbWorldPosition and
// vbWorldNormal. The engine adapters give the shader, the vertex inputs and the uniforms; this
// runs the pass, reads the results back and puts them in the asset's point order.

import { VirtualBonesError } from './errors.js';

const FRAGMENT = `#version 300 es
precision highp float;
out vec4 vbColor;
void main() { vbColor = vec4(0.0); }
`;

/**
 * The world-space tail of a probe's vertex shader: `world` (a mat4 expression) places the skinned
 * vbPosition / vbNormal, the normal by the inverse transpose, normalized. With `previous`, also
 * vbWorldPreviousPosition from vbPreviousPosition (the previous-frame pose, spec/shaders.md
 * "Previous pose"), placed by the same matrix (the runtimes keep no previous instance transform).
 */
export function probeOutputs(world, { previous = false } = {}) {
  return `  mat4 vbWorld = ${world};
  vbWorldPosition = (vbWorld * vec4(vbPosition, 1.0)).xyz;${previous ? `
  vbWorldPreviousPosition = (vbWorld * vec4(vbPreviousPosition, 1.0)).xyz;` : ''}
  vec3 vbN = transpose(inverse(mat3(vbWorld))) * vbNormal;
  float vbLength = length(vbN);
  vbWorldNormal = vbLength > 0.0 ? vbN / vbLength : vbN;
  gl_Position = vec4(0.0, 0.0, 0.0, 1.0);`;
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

/** The outputs a probe program writes: positions, normals and, with `previous`, previous positions. */
export const PROBE_VARYINGS = ['vbWorldPosition', 'vbWorldNormal', 'vbWorldPreviousPosition'];

/**
 * The linked probe program of `vertexSource` (cached per context and `key`); with `previous` the
 * shader also writes vbWorldPreviousPosition (a third transform-feedback output).
 */
export function probeProgram(gl, key, vertexSource, { previous = false } = {}) {
  if (!gl || typeof gl.beginTransformFeedback !== 'function') throw new VirtualBonesError('the probe needs a WebGL 2 context');
  let cache = programs.get(gl);
  if (!cache) programs.set(gl, cache = new Map());
  if (cache.has(key)) return cache.get(key);
  const program = gl.createProgram();
  gl.attachShader(program, compile(gl, gl.VERTEX_SHADER, vertexSource));
  gl.attachShader(program, compile(gl, gl.FRAGMENT_SHADER, FRAGMENT));
  gl.transformFeedbackVaryings(program, PROBE_VARYINGS.slice(0, previous ? 3 : 2), gl.SEPARATE_ATTRIBS);
  gl.linkProgram(program);
  if (!gl.getProgramParameter(program, gl.LINK_STATUS)) throw new VirtualBonesError(`probe program does not link: ${gl.getProgramInfoLog(program)}`);
  cache.set(key, program);
  return program;
}

/**
 * Run `program` over `vertexCount` points of one instance with transform feedback. `setup(input)`
 * is called with the program in use and a fresh vertex array bound: it feeds the vertex inputs
 * through `input.attribute(name, data, size, options)` (options: integer, divisor, offset (bytes),
 * columns (a matN of vec-size columns)) or `input.constant(name, values)` (a generic vertex
 * attribute: the same value for every vertex), and sets uniforms and textures. Returns the
 * [positions, normals] Float32Arrays (3 per vertex), and previous positions for a program made with
 * `previous`. The context's state is the engine's to reset.
 */
export function runFeedback(gl, program, vertexCount, setup) {
  const vao = gl.createVertexArray();
  gl.bindVertexArray(vao);
  gl.useProgram(program);
  const buffers = [];
  const input = {
    attribute(name, data, size, { integer = false, divisor = 0, offset = 0, columns = 1 } = {}) {
      const location = gl.getAttribLocation(program, name);
      if (location < 0) return false;  // optimized out (e.g. normals unused)
      const buffer = gl.createBuffer();
      buffers.push(buffer);
      gl.bindBuffer(gl.ARRAY_BUFFER, buffer);
      gl.bufferData(gl.ARRAY_BUFFER, data, gl.STATIC_DRAW);
      const bytes = data.BYTES_PER_ELEMENT;
      const type = data instanceof Int16Array ? gl.SHORT : data instanceof Uint16Array ? gl.UNSIGNED_SHORT
        : data instanceof Uint32Array ? gl.UNSIGNED_INT : gl.INT;
      for (let c = 0; c < columns; ++c) {
        gl.enableVertexAttribArray(location + c);
        if (integer) gl.vertexAttribIPointer(location + c, size, type, 0, offset);
        else gl.vertexAttribPointer(location + c, size, gl.FLOAT, false, size * columns * bytes, offset + c * size * bytes);
        gl.vertexAttribDivisor(location + c, divisor);
      }
      return true;
    },
    constant(name, values) {
      const location = gl.getAttribLocation(program, name);
      if (location < 0) return false;
      gl.disableVertexAttribArray(location);
      const v = [0, 0, 0, 1].map((d, i) => (i < values.length ? values[i] : d));
      gl.vertexAttrib4f(location, v[0], v[1], v[2], v[3]);
      return true;
    },
    uniform(name) { return gl.getUniformLocation(program, name); },
  };
  setup(input);
  const outputs = Array.from({ length: gl.getProgramParameter(program, gl.TRANSFORM_FEEDBACK_VARYINGS) }, () => gl.createBuffer());
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
  outputs.forEach((_, slot) => gl.bindBufferBase(gl.TRANSFORM_FEEDBACK_BUFFER, slot, null));
  gl.bindTransformFeedback(gl.TRANSFORM_FEEDBACK, null);
  gl.bindVertexArray(null);
  gl.deleteTransformFeedback(feedback);
  gl.deleteVertexArray(vao);
  for (const buffer of [...buffers, ...outputs]) gl.deleteBuffer(buffer);
  return results;
}

/**
 * A mesh's probed [positions, normals, previous positions] in the asset's order: vertex j of an
 * unwelded mesh is face-vertex j of point pointIndex[j]; normals empty for a mesh without normals,
 * previous positions empty where the probe wrote none.
 */
export function assetOrder([positions, normals, previous = null], { pointIndex = null, hasNormals = true, pointCount = 0 }) {
  const points = (values) => {
    if (!pointIndex) return values;
    const out = new Float32Array(pointCount * 3);
    pointIndex.forEach((point, j) => out.set(values.subarray(3 * j, 3 * j + 3), 3 * point));
    return out;
  };
  return [points(positions), hasNormals ? normals : new Float32Array(0), previous ? points(previous) : new Float32Array(0)];
}

/** The arrays one after the other in one Float32Array. */
export function concatenate(arrays) {
  const out = new Float32Array(arrays.reduce((n, a) => n + a.length, 0));
  let at = 0;
  for (const a of arrays) { out.set(a, at); at += a.length; }
  return out;
}

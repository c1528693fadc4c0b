// The previous-frame clock of a crowd (spec virtual-bones.md 21, "Previous-frame pose"; spec/shaders.md
// "Previous pose"): what each instance's previous pose is evaluated with, so that an engine can
// write motion vectors (velocity) for TAA and motion blur. Engine-neutral: the runtimes feed its
// arrays to their shaders (three.js WebGL and WebGPU, Babylon.js) and never recompute the rules.
//
// For a frame interval dt > 0 the previous pose of an instance at scene time t is the instance at
// scene time t - dt by exactly the rules used at t: clip-local time timeOffset + playbackRate *
// (t - dt), wrapped or clamped by the clip (the shader's own clip rule does it), crossfade and
// layers evaluated at t - dt. A reset (the runtime switched the instance's clip or teleported it
// this frame) makes the previous pose the current one: zero velocity.

import { VirtualBonesError } from './errors.js';
import { evaluateSamples } from './playback.js';

/** The frame interval a runtime assumes when it is given none (seconds): 1/60. */
export const DEFAULT_FRAME_INTERVAL = 1 / 60;

/** `dt` if it is a frame interval (finite, > 0), else one clear error. */
export function checkFrameInterval(dt, where = 'frame interval') {
  if (!(Number.isFinite(dt) && dt > 0)) throw new VirtualBonesError(`${where}: the frame interval dt must be a number > 0 (seconds), got ${dt}`);
  return dt;
}

/** The previous frame's clip-local time of an instance: timeOffset + playbackRate * (time - dt). */
export function previousClipTime(timeOffset, playbackRate, time, dt = DEFAULT_FRAME_INTERVAL) {
  return timeOffset + playbackRate * (time - dt);
}

/**
 * Per-instance previous-frame inputs of a crowd of `count` instances.
 *
 * `values` holds 4 floats per instance, the vertex input `vb_instancePreviousFade` of the web
 * runtimes: (fadeTime, fadeWeight, reset, 0) of the previous frame, where fadeTime is the fade
 * clip's clip-local time at t - dt (fadeTimeOffset + fadePlaybackRate * (t - dt), each of them
 * evaluated at t - dt when the fade is time-sampled), fadeWeight the fade weight at t - dt, and
 * reset 1 for an instance reset this frame (its shader then takes the current pose as the
 * previous one; fadeTime and fadeWeight are then the current ones). `previousTime` is the scene
 * time of the previous frame (the uniform `vb_previousTime`): t - dt.
 *
 * Call `update(time, dt, fade)` once per frame, after the current inputs are set (and the
 * time-sampled fades evaluated at `time`); `reset(i)` before it for an instance whose clip was
 * switched or that was teleported: the frame that update prepares has zero velocity for it, the
 * next ones not.
 */
export class PreviousFrame {
  constructor(count) {
    this.count = count;
    this.values = new Float32Array(4 * count);
    this.pending = new Uint8Array(count);
    this.time = 0;
    this.dt = DEFAULT_FRAME_INTERVAL;
    this.previousTime = -DEFAULT_FRAME_INTERVAL;
    this.scratch = null;
  }

  /** Instance `i` was switched to another clip or teleported: no motion vector for it next frame. */
  reset(i) {
    if (!(i >= 0 && i < this.count)) throw new VirtualBonesError(`previous frame: no instance ${i} (${this.count} instances)`);
    this.pending[i] = 1;
  }

  /**
   * The previous-frame inputs for the frame at scene time `time` with interval `dt`. `fade(i)`
   * returns instance i's current [fadeTimeOffset, fadePlaybackRate, fadeWeight]; `samples` are the
   * crowd's time-sampled fade primvars (evaluateSamples' form) or null: a sampled field is taken at
   * time - dt, the others as they are now. Returns `values`.
   */
  update(time, dt, fade, samples = null) {
    checkFrameInterval(dt);
    const previous = time - dt;
    this.time = time;
    this.dt = dt;
    this.previousTime = previous;
    let sampled = null;
    if (samples && Object.keys(samples).length) {
      if (!this.scratch) {
        const n = this.count;
        this.scratch = { fadeClip: new Int32Array(n), fadeTimeOffset: new Float32Array(n), fadePlaybackRate: new Float32Array(n), fadeWeight: new Float32Array(n) };
      }
      sampled = evaluateSamples(samples, previous, this.scratch);
    }
    const values = this.values;
    for (let i = 0; i < this.count; ++i) {
      let [offset, rate, weight] = fade(i);
      const reset = this.pending[i];
      if (!reset && sampled) {
        if (samples.fadeTimeOffset) offset = sampled.fadeTimeOffset[i];
        if (samples.fadePlaybackRate) rate = sampled.fadePlaybackRate[i];
        if (samples.fadeWeight) weight = sampled.fadeWeight[i];
      }
      const at = reset ? time : previous;
      values[4 * i] = offset + rate * at;
      values[4 * i + 1] = Math.min(Math.max(weight, 0), 1);
      values[4 * i + 2] = reset;
      values[4 * i + 3] = 0;
      this.pending[i] = 0;
    }
    return values;
  }
}

// Shader-module assembly: the GLSL of `vbusd shader --lang glsl --no-main --encoding E
// --texel-format F --max-influences K --max-clips C --skin S [--layers] [--max-bones N]`, character
// for character, from the generated modules (shader-modules.js); every runtime builds its shaders
// from these strings and only adds its engine's glue.

import {
  GLSL_MODULES, GLSL_PULLED_MODULES, GLSL_LAYER_BLOCKS, GLSL_LAYER_MARK, BASE_MAX_INFLUENCES, BASE_MAX_CLIPS,
} from './shader-modules.js';
import { VirtualBonesError } from './errors.js';
import { checkSkinBinding, skinRecordTexels, skinRecordWords } from './skin.js';
import { LAYER_MASK_SPAN } from './additive.js';

/** Bones the compact module's range uniforms hold unless an animation needs more (VB_MAX_BONES). */
export const BASE_MAX_BONES = 64;

/** `text` with `search`, which must occur exactly once, replaced. */
export function replaceOnce(text, search, replacement) {
  const at = text.indexOf(search);
  if (at < 0 || text.indexOf(search, at + 1) >= 0) throw new VirtualBonesError(`shader hook ${JSON.stringify(search.trim())} not found exactly once`);
  return text.slice(0, at) + replacement + text.slice(at + search.length);
}

/**
 * The GLSL of `vbusd shader --lang glsl --no-main --encoding E --texel-format F
 * --max-influences K --max-clips C --skin S [--layers] [--max-bones N]`, character for character.
 * The layer functions of format 1.2 (spec/shaders.md, "Layers") come with the attribute binding only.
 */
export function shaderModule(encoding, texelFormat, maxInfluences = BASE_MAX_INFLUENCES, maxClips = BASE_MAX_CLIPS, skin = 'attributes', layers = false, maxBones = BASE_MAX_BONES) {
  checkSkinBinding(skin);
  if (layers && skin !== 'attributes') throw new VirtualBonesError('layers (format 1.2) need the attributes skin binding');
  const base = (skin === 'pulled' ? GLSL_PULLED_MODULES : GLSL_MODULES)[`${encoding}/${texelFormat}`];
  if (base === undefined) throw new VirtualBonesError(`no shader module for encoding ${encoding}, texel format ${texelFormat}`);
  if (!Number.isInteger(maxInfluences) || maxInfluences < 1 || maxInfluences > 8) {
    throw new VirtualBonesError(`maxInfluences must be 1..8, got ${maxInfluences}`);
  }
  if (!Number.isInteger(maxClips) || maxClips < 1 || maxClips > 256) {
    throw new VirtualBonesError(`maxClips must be 1..256, got ${maxClips}`);
  }
  let text = replaceOnce(replaceOnce(replaceOnce(base,
    `up to ${BASE_MAX_INFLUENCES} influences.`, `up to ${maxInfluences} influences.`),
  `#define VB_MAX_INFLUENCES ${BASE_MAX_INFLUENCES}\n`, `#define VB_MAX_INFLUENCES ${maxInfluences}\n`),
  `#define VB_MAX_CLIPS ${BASE_MAX_CLIPS}\n`, `#define VB_MAX_CLIPS ${maxClips}\n`);
  if (encoding === 'compactQuatTranslation') {  // `vbusd shader --max-bones N`: the range uniforms' size
    if (!Number.isInteger(maxBones) || maxBones < 1 || maxBones > 1024) throw new VirtualBonesError(`maxBones must be 1..1024, got ${maxBones}`);
    text = replaceOnce(text, `#define VB_MAX_BONES ${BASE_MAX_BONES}\n`, `#define VB_MAX_BONES ${maxBones}\n`);
  }
  if (skin === 'pulled') {
    text = replaceOnce(replaceOnce(text,
      `#define VB_SKIN_WORDS ${skinRecordWords(BASE_MAX_INFLUENCES)}\n`, `#define VB_SKIN_WORDS ${skinRecordWords(maxInfluences)}\n`),
    `#define VB_SKIN_TEXELS ${skinRecordTexels(BASE_MAX_INFLUENCES)}\n`, `#define VB_SKIN_TEXELS ${skinRecordTexels(maxInfluences)}\n`);
  }
  if (layers) text = replaceOnce(text, GLSL_LAYER_MARK, GLSL_LAYER_BLOCKS[encoding] + GLSL_LAYER_MARK);
  return text;
}

/**
 * The module for a shader preprocessor that runs in JavaScript before the GPU compiler and reads
 * a bare `#if NAME` as `#if defined(NAME)` (Babylon.js'), which would switch the module's
 * `#define VB_MAIN 0` example main on. Each bare `#if VB_X` becomes `#if VB_X > 0`: the same test
 * for the module's integer macros in a C preprocessor, and one such a preprocessor evaluates by
 * value. Nothing else of the module changes.
 */
export function definedTestModule(text) {
  return text.replace(/^#if (VB_[A-Z0-9_]+)[ \t]*$/gm, '#if $1 > 0');
}

/**
 * GLSL statements for the top of a vertex shader's main(), the same in every engine: the vertex's
 * influences (from the bone inputs vb_boneIndices0/1 and vb_boneWeights0/1, integer or float
 * vectors, or with the pulled skin from its record by gl_VertexID), then the module's
 * vbSkinCrossfade (spec 8.3; fade weight 0 is exactly vbSkin) or, with layers, vbSkinLayered
 * (8.6; every layer weight 0 is exactly vbSkinCrossfade), skinning `position` / `normal` (the rest
 * vertex) into the `vbPosition` / `vbNormal` they declare. An engine only names where an
 * instance's playback comes from: `playback` holds GLSL expressions `clip`, `tau`, `fadeClip`,
 * `fadeTau`, `fadeWeight` and, with layers, those of layer `j` (a GLSL int): `layerClip`,
 * `layerMask` (an int: the packed code of additive.js' packLayerMask, mask and additive reference
 * clip), `layerTau`, `layerWeight` and `referenceTau` (the additive reference pose's clip-local
 * time). The layered module must be preceded by ADDITIVE_LAYERS_DEFINE.
 */
export function skinningStatements({ skin = 'attributes', layers = false, position = 'position', normal = 'normal', playback }) {
  checkSkinBinding(skin);
  const influences = skin === 'pulled' ? `
  int vbIndex[VB_MAX_INFLUENCES];
  float vbWeight[VB_MAX_INFLUENCES];
  vbSkinInfluences(gl_VertexID, vbIndex, vbWeight);` : `
  int vbIndex[VB_MAX_INFLUENCES];
  float vbWeight[VB_MAX_INFLUENCES];
  for (int i = 0; i < VB_MAX_INFLUENCES; ++i) {
#if VB_MAX_INFLUENCES > 4
    vbIndex[i] = int(i < 4 ? vb_boneIndices0[i] : vb_boneIndices1[i - 4]);
    vbWeight[i] = i < 4 ? vb_boneWeights0[i] : vb_boneWeights1[i - 4];
#else
    vbIndex[i] = int(vb_boneIndices0[i]);
    vbWeight[i] = vb_boneWeights0[i];
#endif
  }`;
  const p = playback;
  const instance = `${p.clip}, ${p.tau},
                  ${p.fadeClip}, ${p.fadeTau}, ${p.fadeWeight},`;
  if (!layers) {
    return `${influences}
  vec3 vbPosition;
  vec3 vbNormal;
  vbSkinCrossfade(${instance}
                  ${position}, ${normal}, vbIndex, vbWeight, vbPosition, vbNormal);
`;
  }
  // Additive layers (format 1.3, additive.js): the mask slot holds mask + span x (reference clip + 1)
  // for an additive layer; the module runs with VB_ADDITIVE_LAYERS 1 (ADDITIVE_LAYERS_DEFINE).
  return `${influences}
  vec3 vbPosition;
  vec3 vbNormal;
  int vbLayerClip[VB_MAX_LAYERS];
  float vbLayerTau[VB_MAX_LAYERS];
  float vbLayerWeight[VB_MAX_LAYERS];
  int vbLayerMask[VB_MAX_LAYERS];
  int vbLayerMode[VB_MAX_LAYERS];
  int vbReferenceClip[VB_MAX_LAYERS];
  float vbReferenceTau[VB_MAX_LAYERS];
  for (int j = 0; j < VB_MAX_LAYERS; ++j) {
    int vbCode = ${p.layerMask};
    vbLayerClip[j] = ${p.layerClip};
    vbLayerMask[j] = vbCode % ${LAYER_MASK_SPAN};
    vbLayerMode[j] = vbCode >= ${LAYER_MASK_SPAN} ? 1 : 0;
    vbReferenceClip[j] = max(vbCode / ${LAYER_MASK_SPAN} - 1, 0);
    vbReferenceTau[j] = ${p.referenceTau};
    vbLayerTau[j] = ${p.layerTau};
    vbLayerWeight[j] = ${p.layerWeight};
  }
  vbSkinLayered(${instance}
                vbLayerClip, vbLayerTau, vbLayerWeight, vbLayerMask, vbLayerMode, vbReferenceClip, vbReferenceTau,
                ${position}, ${normal}, vbIndex, vbWeight, vbPosition, vbNormal);
`;
}

/**
 * Declarations of the previous-frame inputs (spec virtual-bones.md 21, spec/shaders.md "Previous
 * pose") the web runtimes feed from @vbusd/core's PreviousFrame: the per-instance stream
 * `vb_instancePreviousFade` = (fadeTime, fadeWeight, reset, 0), whose x and y are the GLSL module's
 * `vb_instancePreviousFade` (the fade clip's clip-local time and the fade weight of the previous
 * frame) and whose z marks an instance reset this frame, and the uniform `vb_previousTime`.
 * `keyword`: `in`, or `attribute` for an engine's GLSL 1 style shaders.
 */
export function previousDeclarations(keyword = 'in') {
  return `${keyword} vec4 vb_instancePreviousFade;
uniform float vb_previousTime;
`;
}

/** `expression` (a clip-local time of `skinningStatements`' playback) at the previous frame: vb_time, once, as vb_previousTime. */
function atPreviousTime(expression, what) {
  const uses = expression.match(/\bvb_time\b/g) ?? [];
  if (uses.length !== 1) throw new VirtualBonesError(`previous pose: the playback's ${what} must use vb_time once, got ${JSON.stringify(expression)}`);
  return expression.replace(/\bvb_time\b/, 'vb_previousTime');
}

/**
 * GLSL statements after `skinningStatements` (in its scope, with the same `playback`): the
 * previous-frame skinned position (spec virtual-bones.md 21, spec/shaders.md "Previous pose") into
 * `target` (declared here unless `declare` is false), the same skin function as the current pose
 * at the previous frame's times: the clip's and layers' `tau` / `layerTau` with vb_time replaced by
 * vb_previousTime (each instance its own offset and rate; the clip wraps or clamps there), the fade
 * clip at vb_instancePreviousFade.x with weight vb_instancePreviousFade.y, the layers' clips,
 * masks and weights as now. An instance reset this frame (vb_instancePreviousFade.z = 1) keeps its
 * current pose: zero velocity.
 */
export function previousSkinningStatements({ layers = false, position = 'position', normal = 'normal', target = 'vbPreviousPosition', declare = true, playback }) {
  const p = playback;
  const instance = `${p.clip}, ${atPreviousTime(p.tau, 'tau')},
                    ${p.fadeClip}, vb_instancePreviousFade.x, vb_instancePreviousFade.y,`;
  const call = layers ? `for (int j = 0; j < VB_MAX_LAYERS; ++j) {
      vbLayerTau[j] = ${atPreviousTime(p.layerTau, 'layerTau')};
    }
    vbSkinLayered(${instance}
                  vbLayerClip, vbLayerTau, vbLayerWeight, vbLayerMask, vbLayerMode, vbReferenceClip, vbReferenceTau,
                  ${position}, ${normal}, vbIndex, vbWeight, ${target}, vbPreviousNormal);` : `vbSkinCrossfade(${instance}
                    ${position}, ${normal}, vbIndex, vbWeight, ${target}, vbPreviousNormal);`;
  return `
  ${declare ? 'vec3 ' : ''}${target} = vbPosition;
  if (vb_instancePreviousFade.z < 0.5) {
    vec3 vbPreviousNormal;
    ${call}
  }
`;
}

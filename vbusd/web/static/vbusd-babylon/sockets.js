// Sockets on the CPU (spec/virtual-bones.md 8.4, format 1.1) for Babylon crowds: the three.js
// runtime's decoder of a bone's transform (web/src/sockets.js: socketMatrix, which reads the
// animation's own texels as a decoder does), placed by the thin instance and the mesh. three's
// Matrix4 `elements` (column-major, column vectors) are Babylon's row-vector `m`, number for number.

import { Matrix } from '@babylonjs/core';
import { socketMatrix as decodeSocket } from '@vbusd/three';

const ENCODINGS = { crossMatrix: 3, affineMatrix: 3, quatTranslation: 2, dualQuat: 2 };

// The fields the three.js decoder reads, from a Babylon VirtualBonesAnimation.
function decoderView(animation) {
  return { name: animation.name, layout: animation.layout, clips: animation.clips, encoding: animation.encoding,
    texelFormat: animation.texelFormat, texelsPerBone: ENCODINGS[animation.encoding], texture: { image: { data: animation.texels } } };
}

/**
 * Socket of instance `index` of `crowd` (a VirtualBonesCrowd): the world transform of `bone` at
 * scene time `time` (clip, offset, rate and crossfade of the instance; its thin-instance matrix and
 * the mesh's world matrix) as a Babylon Matrix: a prop follows each character's hand with it.
 */
export function crowdSocketMatrix(crowd, index, bone, time) {
  const [clip, offset, rate, fadeClip] = crowd.instanceA.subarray(4 * index, 4 * index + 4);
  const [fadeOffset, fadeRate, fadeWeight] = crowd.instanceB.subarray(4 * index, 4 * index + 3);
  const joint = decodeSocket(decoderView(crowd.animation), bone, Math.round(clip), offset + rate * time,
    { clip: Math.round(fadeClip), tau: fadeOffset + fadeRate * time, weight: fadeWeight });
  // Row vectors: the joint first, then the instance's placement, then the mesh's world.
  return Matrix.FromArray(joint.elements).multiply(crowd.instanceMatrix(index)).multiply(crowd.meshes[0].computeWorldMatrix(true));
}

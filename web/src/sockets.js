// Sockets and root motion on the CPU (spec/virtual-bones.md 8.4 and 8.5, format 1.1): where to attach
// a prop to a bone of each instance, and how far a clip baked in place moves its instance, as
// three.js Matrix4s. The decoder is @vbusd/core's (the same math as vbusd.decoders.reference:
// joint_transforms, crowd_joint_transforms, root_motion), reading the animation's stored texels.

import { Matrix4 } from 'three';
import { rowPosition, boneRows, layeredJointElements, rootMotionElements } from '@vbusd/core';

export { rowPosition, boneRows };

/**
 * Socket (spec 8.4): the joint transform J = M B of `bone` in animation space at clip-local time
 * `tau`, as a Matrix4. `fade` ({clip, tau, weight}) crossfades the decoded matrices,
 * M = (1 - w) M_a + w M_b. The bind transforms come from the layout's `bindTransforms`. `layers`
 * ([{clip, tau, weight, mask}], spec 8.6) layer each side of the crossfade (@vbusd/core's
 * layeredJointElements).
 */
export function socketMatrix(animation, bone, clipIndex, tau, fade = null, layers = null) {
  return new Matrix4().fromArray(layeredJointElements(animation, bone, clipIndex, tau, fade, layers));
}

/**
 * Root motion (spec 8.5): D(t1) D(t0)^-1 of a clip baked in place, as a Matrix4 in animation space
 * (the identity without a root track). `rootMotion` is {upAxis, tracks: [[[dx, dy, dz, yaw], ...]]}.
 */
export function rootMotionMatrix(animation, rootMotion, clipIndex, t0, t1) {
  return new Matrix4().fromArray(rootMotionElements(animation, rootMotion, clipIndex, t0, t1));
}

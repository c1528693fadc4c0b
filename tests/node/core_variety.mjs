// @vbusd/core's crowd variety helpers (web/core/src/variety.js) on given inputs; prints JSON.
import { instanceColors, partBit, partMatrices, partMatrixAt, varietyOf, packageVariety } from '../../web/core/src/variety.js';
import { moveInstance } from '../../web/core/src/playback.js';

const instances = {
  count: 3,
  tint: new Float32Array([1, 0.5, 0, 0.25, 1, 1, 1, 1, 1]),
  variant: new Int32Array([1, 0, -1]),
  parts: new Int32Array([1, 0, 3]),
  variantNames: ['home', 'away'],
  variantColors: [[0.8, 0.8, 0.8], [0.2, 0.3, 0.8]],
  partNames: ['Hat', 'Flag'],
};
const identity = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1];
const matrices = new Float32Array([...identity, ...identity, ...identity]);
for (let i = 0; i < 3; ++i) matrices[16 * i + 12] = i;  // translations x = 0, 1, 2
const json = {
  meshes: [{ primitives: [
    { extensions: { VBUSD_virtual_bones: { animation: 0, influences: 4, path: '/C/Body' },
      KHR_materials_variants: { mappings: [{ material: 0, variants: [0] }, { material: 1, variants: [1] }] } } },
    { extensions: { VBUSD_virtual_bones: { animation: 0, influences: 1, path: '/C/Hat', part: 0 } } },
  ] }],
  materials: [{ pbrMetallicRoughness: { baseColorFactor: [0.8, 0.8, 0.8, 1] } },
    { pbrMetallicRoughness: { baseColorFactor: [0.2, 0.3, 0.8, 1] } }],
  extensions: { KHR_materials_variants: { variants: [{ name: 'home' }, { name: 'away' }] } },
};
// A placement turned 90 degrees about Y (its +Z heading becomes +X) at x = 1, moved 2 along its own +Z.
const turned = new Float32Array([0, 0, -1, 0, 0, 1, 0, 0, 1, 0, 0, 0, 1, 0, 0, 1]);
const fromPackage = packageVariety(json, 0, { tint: [1, 1, 1, 0, 0, 1], variant: [1, 0], parts: [1, 0] }, 2);
console.log(JSON.stringify({
  colors: Array.from(instanceColors(instances)),
  bits: [partBit('/C/Characters/x/Hat', instances.partNames), partBit('Flag', instances.partNames), partBit('/C/Body', instances.partNames)],
  hat: Array.from(partMatrices(matrices, instances.parts, 0)),
  flag: Array.from(partMatrices(matrices, instances.parts, 1)),
  body: Array.from(partMatrices(matrices, instances.parts, -1)),
  levelSlots: [Array.from(partMatrixAt(new Float32Array(32), 1, matrices, 2, 1, 1)), Array.from(partMatrixAt(new Float32Array(32), 0, matrices, 2, 3, 1))],
  moved: Array.from(moveInstance(turned, 0, [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 2, 1])),
  variety: [0, 1, 2].map((i) => varietyOf(instances, i)),
  fromPackage: { ...fromPackage, tint: Array.from(fromPackage.tint), variant: Array.from(fromPackage.variant), parts: Array.from(fromPackage.parts) },
}));

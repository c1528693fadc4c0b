// @vbusd/core's crowd variety helpers (web/core/src/variety.js) on given inputs; prints JSON.
import { instanceColors, partBit, partMatrices, varietyOf, packageVariety } from '../../web/core/src/variety.js';

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
const fromPackage = packageVariety(json, 0, { tint: [1, 1, 1, 0, 0, 1], variant: [1, 0], parts: [1, 0] }, 2);
console.log(JSON.stringify({
  colors: Array.from(instanceColors(instances)),
  bits: [partBit('/C/Characters/x/Hat', instances.partNames), partBit('Flag', instances.partNames), partBit('/C/Body', instances.partNames)],
  hat: Array.from(partMatrices(matrices, instances.parts, 0)),
  flag: Array.from(partMatrices(matrices, instances.parts, 1)),
  body: Array.from(partMatrices(matrices, instances.parts, -1)),
  variety: [0, 1, 2].map((i) => varietyOf(instances, i)),
  fromPackage: { ...fromPackage, tint: Array.from(fromPackage.tint), variant: Array.from(fromPackage.variant), parts: Array.from(fromPackage.parts) },
}));

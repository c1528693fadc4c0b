// Read a package with the VBUSD_virtual_bones extension, run dedup, prune, flatten and weld on it,
// and write it back: `node test/transform_file.mjs IN.glb OUT.glb` (tests/test_gltf_package_blending.py
// checks that a crowd's fade and layer attributes and their time samples survive).
import fs from 'node:fs';

import { dedup, flatten, prune, weld } from '@gltf-transform/functions';

import { createIO } from './helpers.mjs';

const io = await createIO();
const document = await io.readBinary(new Uint8Array(fs.readFileSync(process.argv[2])));
await document.transform(dedup(), prune(), flatten(), weld());
fs.writeFileSync(process.argv[3], await io.writeBinary(document));

// Print the Khronos glTF-Validator's report of a GLB as JSON (for tests/test_gltf_transform.py).
// Usage: node test/validate.mjs FILE.glb
import fs from 'node:fs';

import { validate } from './helpers.mjs';

process.stdout.write(JSON.stringify(await validate(new Uint8Array(fs.readFileSync(process.argv[2])))));

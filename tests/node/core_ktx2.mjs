// Parse a KTX2 file with @vbusd/core's parser (web/core/src/ktx2.js, what every engine's glTF
// loader runs) and with ktx-parse (the parser three.js's KTX2Loader uses), and print both as JSON,
// for tests/test_core_ktx2.py. Zstandard levels are inflated with the zstddec three ships.
// Usage: node core_ktx2.mjs FILE.ktx2
import fs from 'node:fs';
import { read } from 'ktx-parse';
import { ZSTDDecoder } from 'three/examples/jsm/libs/zstddec.module.js';

import { parseVirtualBonesKTX2, readKTX2Container } from '../../web/core/src/ktx2.js';

const bytes = new Uint8Array(fs.readFileSync(process.argv[2]));
const b64 = (u8) => Buffer.from(u8.buffer, u8.byteOffset, u8.byteLength).toString('base64');
const zstd = new ZSTDDecoder();
await zstd.init();
const result = {};
try {
  const c = readKTX2Container(bytes, 'file.ktx2');
  const reference = read(bytes);
  const fields = ['vkFormat', 'typeSize', 'pixelWidth', 'pixelHeight', 'pixelDepth', 'layerCount', 'faceCount', 'levelCount', 'supercompressionScheme'];
  result.container = Object.fromEntries(fields.map((key) => [key, c[key]]));
  result.ktxParse = Object.fromEntries(fields.map((key) => [key, reference[key]]));
  result.keys = Object.keys(c.keyValue).sort();
  result.ktxParseKeys = Object.keys(reference.keyValue).sort();
  result.levelsEqual = c.levels.length === reference.levels.length && c.levels.every((level, i) =>
    Buffer.compare(Buffer.from(level.levelData), Buffer.from(reference.levels[i].levelData)) === 0
    && level.uncompressedByteLength === reference.levels[i].uncompressedByteLength);
  const parsed = await parseVirtualBonesKTX2(bytes, 'file.ktx2', { inflate: (data, size) => zstd.decode(data, size) });
  result.layout = parsed.layout;
  result.texels = b64(new Uint8Array(parsed.texels.buffer, parsed.texels.byteOffset, parsed.texels.byteLength));
} catch (error) {
  result.error = String(error && error.message || error);
}
process.stdout.write(JSON.stringify(result));

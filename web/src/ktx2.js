// The Virtual Bones KTX2 parser is @vbusd/core's (web/core/src/ktx2.js); the three.js runtime
// hands it the Zstandard decoder three ships (three/addons/libs/zstddec.module.js), so a package
// with supercompressed textures needs nothing beyond three.

import { parseVirtualBonesKTX2 as parse } from '@vbusd/core';
import { ZSTDDecoder } from 'three/addons/libs/zstddec.module.js';

let zstd = null;

async function inflate(data, size) {
  if (zstd === null) {
    zstd = new ZSTDDecoder();
    await zstd.init();
  }
  return zstd.decode(data, size);
}

/** @vbusd/core's parseVirtualBonesKTX2 with three's Zstandard decoder. */
export function parseVirtualBonesKTX2(bytes, name = 'texture.ktx2') {
  return parse(bytes, name, { inflate });
}

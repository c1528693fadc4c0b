// Read a KTX2 file with ktx-parse (the parser three.js's KTX2Loader uses) and with KTX2Loader
// itself, and print what each found as JSON, for tests/test_ktx2.py to compare with vbusd's own
// writer bit for bit. Usage: node ktx2_read.mjs FILE.ktx2
import fs from 'node:fs';
import { read } from 'ktx-parse';
import * as THREE from 'three';
import { KTX2Loader } from 'three/examples/jsm/loaders/KTX2Loader.js';

const bytes = new Uint8Array(fs.readFileSync(process.argv[2]));
const b64 = (u8) => Buffer.from(u8.buffer, u8.byteOffset, u8.byteLength).toString('base64');
const result = {};
try {
  const c = read(bytes);
  const keyValue = {};
  for (const [key, value] of Object.entries(c.keyValue)) {
    keyValue[key] = typeof value === 'string' ? { string: value } : { base64: b64(value) };
  }
  result.ktxParse = {
    vkFormat: c.vkFormat, typeSize: c.typeSize, pixelWidth: c.pixelWidth, pixelHeight: c.pixelHeight,
    pixelDepth: c.pixelDepth, layerCount: c.layerCount, faceCount: c.faceCount, levelCount: c.levelCount,
    supercompressionScheme: c.supercompressionScheme, dataFormatDescriptor: c.dataFormatDescriptor,
    keyValue, globalDataLength: c.globalData ? c.globalData.byteLength : 0,
    levels: c.levels.map((l) => ({ base64: b64(l.levelData), uncompressedByteLength: l.uncompressedByteLength })),
  };
} catch (error) {
  result.ktxParseError = String(error && error.message || error);
}
try {
  const loader = new KTX2Loader();
  // detectSupport(renderer) needs a WebGL context; raw (non-Basis) textures need no transcoder, so
  // the capabilities it would record are not consulted on this path.
  loader.workerConfig = { astcSupported: false, astcHDRSupported: false, etc1Supported: false,
    etc2Supported: false, dxtSupported: false, bptcSupported: false, pvrtcSupported: false };
  const texture = await loader._createTexture(bytes.slice().buffer);
  const data = texture.mipmaps[0].data;
  result.ktx2Loader = {
    isDataTexture: !!texture.isDataTexture, width: texture.image.width, height: texture.image.height,
    type: texture.type, format: texture.format, colorSpace: texture.colorSpace, flipY: texture.flipY,
    generateMipmaps: texture.generateMipmaps, minFilter: texture.minFilter, magFilter: texture.magFilter,
    normalized: !!texture.normalized, mipmapCount: texture.mipmaps.length,
    dataType: data.constructor.name, base64: b64(new Uint8Array(data.buffer, data.byteOffset, data.byteLength)),
  };
  result.three = { HalfFloatType: THREE.HalfFloatType, FloatType: THREE.FloatType,
    UnsignedShortType: THREE.UnsignedShortType, RGBAFormat: THREE.RGBAFormat,
    NoColorSpace: THREE.NoColorSpace, LinearSRGBColorSpace: THREE.LinearSRGBColorSpace,
    NearestFilter: THREE.NearestFilter };
} catch (error) {
  result.ktx2LoaderError = String(error && error.message || error);
}
process.stdout.write(JSON.stringify(result));

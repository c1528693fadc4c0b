// A Virtual Bones texture from a KTX 2.0 file (spec/ktx2.md): parsed with ktx-parse (the parser
// three's KTX2Loader uses), Zstandard levels inflated with zstddec (also shipped with three), the
// layout metadata from the `vbusd.layout` key/value entry. Row 0 of the file is texture row 0.

import { read } from 'three/addons/libs/ktx-parse.module.js';
import { ZSTDDecoder } from 'three/addons/libs/zstddec.module.js';

import { VirtualBonesError } from './animation.js';

const FORMATS = {
  97: { texelFormat: 'float16', typeSize: 2, array: Uint16Array },   // VK_FORMAT_R16G16B16A16_SFLOAT
  109: { texelFormat: 'float32', typeSize: 4, array: Float32Array },  // VK_FORMAT_R32G32B32A32_SFLOAT
  91: { texelFormat: 'unorm16', typeSize: 2, array: Uint16Array },    // VK_FORMAT_R16G16B16A16_UNORM
  104: { texelFormat: 'uint32', typeSize: 4, array: Uint32Array, channels: 3 },  // VK_FORMAT_R32G32B32_UINT (format 1.2)
};

let zstd = null;

async function inflate(data, size) {
  if (zstd === null) {
    zstd = new ZSTDDecoder();
    await zstd.init();
  }
  return zstd.decode(data, size);
}

async function sha256(bytes) {
  if (!globalThis.crypto?.subtle) return null;  // not a secure context: skip the digest check
  const digest = new Uint8Array(await globalThis.crypto.subtle.digest('SHA-256', bytes));
  return `sha256:${Array.from(digest, (b) => b.toString(16).padStart(2, '0')).join('')}`;
}

/**
 * Parse a Virtual Bones KTX2 file.
 *
 * @param {Uint8Array|ArrayBuffer} bytes the whole file
 * @param {string} name for messages
 * @returns {Promise<{layout: object, texels: Uint16Array|Float32Array}>} the layout metadata and
 *   the stored texel values, scanline 0 first
 */
export async function parseVirtualBonesKTX2(bytes, name = 'texture.ktx2') {
  const data = bytes instanceof Uint8Array ? bytes : new Uint8Array(bytes);
  let container;
  try {
    container = read(data);
  } catch (error) {
    throw new VirtualBonesError(`${name}: not a KTX2 file (${error.message})`);
  }
  const format = FORMATS[container.vkFormat];
  if (!format) throw new VirtualBonesError(`${name}: vkFormat ${container.vkFormat} is not a Virtual Bones format (97, 109, 91 or 104)`);
  if (container.levelCount !== 1 || container.layerCount !== 0 || container.faceCount !== 1 || container.pixelDepth !== 0) {
    throw new VirtualBonesError(`${name}: not a single 2D level (levels ${container.levelCount}, layers ${container.layerCount}, faces ${container.faceCount})`);
  }
  const orientation = container.keyValue.KTXorientation;
  if (orientation !== undefined && orientation !== 'rd') throw new VirtualBonesError(`${name}: KTXorientation ${JSON.stringify(orientation)} is not "rd"`);
  const entry = container.keyValue['vbusd.layout'];
  if (!entry) throw new VirtualBonesError(`${name}: no vbusd.layout key/value entry: not a Virtual Bones texture`);
  const text = new TextDecoder().decode(entry);
  let layout;
  try {
    layout = JSON.parse(text.endsWith('\0') ? text.slice(0, -1) : text);
  } catch (error) {
    throw new VirtualBonesError(`${name}: vbusd.layout is not JSON (${error.message})`);
  }
  if (layout.texelFormat !== format.texelFormat) throw new VirtualBonesError(`${name}: vkFormat ${container.vkFormat} is ${format.texelFormat}, the metadata says ${layout.texelFormat}`);
  if (layout.width !== container.pixelWidth || layout.height !== container.pixelHeight) {
    throw new VirtualBonesError(`${name}: ${container.pixelWidth} x ${container.pixelHeight} texels, the metadata says ${layout.width} x ${layout.height}`);
  }
  const level = container.levels[0];
  const size = layout.width * layout.height * (format.channels ?? 4) * format.typeSize;
  if (level.uncompressedByteLength !== size) throw new VirtualBonesError(`${name}: level 0 holds ${level.uncompressedByteLength} bytes, ${size} expected`);
  let levelData;
  if (container.supercompressionScheme === 0) levelData = level.levelData;
  else if (container.supercompressionScheme === 2) levelData = await inflate(level.levelData, size);
  else throw new VirtualBonesError(`${name}: supercompression scheme ${container.supercompressionScheme} is not supported (0 or 2)`);
  if (levelData.byteLength !== size) throw new VirtualBonesError(`${name}: level 0 inflates to ${levelData.byteLength} bytes, ${size} expected`);
  const copy = new Uint8Array(size);  // aligned, and independent of the file's buffer
  copy.set(levelData);
  const digest = await sha256(copy);
  if (digest !== null && layout.contentDigest && digest !== layout.contentDigest) {
    throw new VirtualBonesError(`${name}: texel data digest ${digest} differs from the metadata's ${layout.contentDigest}`);
  }
  return { layout, texels: new format.array(copy.buffer) };
}

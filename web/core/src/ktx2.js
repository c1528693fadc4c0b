// A Virtual Bones texture from a KTX 2.0 file (spec/ktx2.md): the container read here (header,
// level index, key/value data: the fields spec/ktx2.md uses), Zstandard levels inflated with
// zstddec (three.js ships it as three/addons/libs/zstddec.module.js; the viewer pages map the bare
// name `zstddec` to that file), the layout metadata from the `vbusd.layout` key/value entry. Row 0
// of the file is texture row 0. Engine-neutral: every runtime's glTF loader parses the package's
// KTX2 buffer views with it.

import { VirtualBonesError } from './errors.js';

const IDENTIFIER = [0xab, 0x4b, 0x54, 0x58, 0x20, 0x32, 0x30, 0xbb, 0x0d, 0x0a, 0x1a, 0x0a];

const FORMATS = {
  97: { texelFormat: 'float16', typeSize: 2, array: Uint16Array },   // VK_FORMAT_R16G16B16A16_SFLOAT
  109: { texelFormat: 'float32', typeSize: 4, array: Float32Array },  // VK_FORMAT_R32G32B32A32_SFLOAT
  91: { texelFormat: 'unorm16', typeSize: 2, array: Uint16Array },    // VK_FORMAT_R16G16B16A16_UNORM
  104: { texelFormat: 'uint32', typeSize: 4, array: Uint32Array, channels: 3 },  // VK_FORMAT_R32G32B32_UINT (format 1.2)
};

/**
 * The KTX2 container of `data` (a Uint8Array): `{vkFormat, typeSize, pixelWidth, pixelHeight,
 * pixelDepth, layerCount, faceCount, levelCount, supercompressionScheme, keyValue: {key: Uint8Array},
 * levels: [{levelData: Uint8Array, uncompressedByteLength}]}`, every region checked to lie inside
 * the file (ktx2.md, "Reading safely").
 */
export function readKTX2Container(data, name = 'texture.ktx2') {
  const fail = (what) => { throw new VirtualBonesError(`${name}: not a KTX2 file (${what})`); };
  if (data.byteLength < 80 || IDENTIFIER.some((byte, i) => data[i] !== byte)) fail('no KTX 2.0 identifier');
  const view = new DataView(data.buffer, data.byteOffset, data.byteLength);
  const u32 = (at) => view.getUint32(at, true);
  const u64 = (at) => {
    const high = view.getUint32(at + 4, true);
    if (high !== 0) fail(`a 64-bit field at byte ${at} beyond 4 GiB`);
    return view.getUint32(at, true);
  };
  const within = (offset, length, what) => {
    if (offset + length > data.byteLength) fail(`${what} (bytes ${offset}..${offset + length}) past the end of the ${data.byteLength}-byte file`);
  };
  const container = {
    vkFormat: u32(12), typeSize: u32(16), pixelWidth: u32(20), pixelHeight: u32(24), pixelDepth: u32(28),
    layerCount: u32(32), faceCount: u32(36), levelCount: u32(40), supercompressionScheme: u32(44), keyValue: {}, levels: [],
  };
  const kvdOffset = u32(56);
  const kvdLength = u32(60);
  const levels = Math.max(container.levelCount, 1);
  within(80, 24 * levels, 'the level index');
  for (let level = 0; level < levels; ++level) {
    const at = 80 + 24 * level;
    const offset = u64(at);
    const length = u64(at + 8);
    within(offset, length, `level ${level}`);
    container.levels.push({ levelData: data.subarray(offset, offset + length), uncompressedByteLength: u64(at + 16) });
  }
  within(kvdOffset, kvdLength, 'the key/value data');
  for (let at = kvdOffset; at + 4 <= kvdOffset + kvdLength;) {
    const length = u32(at);
    within(at + 4, length, 'a key/value entry');
    const entry = data.subarray(at + 4, at + 4 + length);
    const end = entry.indexOf(0);
    if (end < 0) fail(`a key/value entry at byte ${at} without a NUL after its key`);
    container.keyValue[new TextDecoder().decode(entry.subarray(0, end))] = entry.subarray(end + 1);
    at += 4 + length + (-(4 + length) & 3);
  }
  return container;
}

let zstd = null;

async function zstdInflate(data, size) {
  if (zstd === null) {
    let ZSTDDecoder;
    try {
      ({ ZSTDDecoder } = await import('zstddec'));
    } catch (error) {
      throw new VirtualBonesError(`a Zstandard-supercompressed KTX2 level needs the zstddec module (npm install zstddec, map it in the page's import map, or pass parseVirtualBonesKTX2's inflate option): ${error.message}`);
    }
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
 * @param {{inflate?: (data: Uint8Array, size: number) => Promise<Uint8Array>}} options how to
 *   inflate a Zstandard level (default: zstddec, imported when a file needs it)
 * @returns {Promise<{layout: object, texels: Uint16Array|Float32Array|Uint32Array}>} the layout
 *   metadata and the stored texel values, scanline 0 first
 */
export async function parseVirtualBonesKTX2(bytes, name = 'texture.ktx2', { inflate = zstdInflate } = {}) {
  const data = bytes instanceof Uint8Array ? bytes : new Uint8Array(bytes);
  const container = readKTX2Container(data, name);
  const format = FORMATS[container.vkFormat];
  if (!format) throw new VirtualBonesError(`${name}: vkFormat ${container.vkFormat} is not a Virtual Bones format (97, 109, 91 or 104)`);
  if (container.levelCount !== 1 || container.layerCount !== 0 || container.faceCount !== 1 || container.pixelDepth !== 0) {
    throw new VirtualBonesError(`${name}: not a single 2D level (levels ${container.levelCount}, layers ${container.layerCount}, faces ${container.faceCount})`);
  }
  const text = (value) => {
    const decoded = new TextDecoder().decode(value);
    return decoded.endsWith('\0') ? decoded.slice(0, -1) : decoded;
  };
  const orientation = container.keyValue.KTXorientation && text(container.keyValue.KTXorientation);
  if (orientation !== undefined && orientation !== 'rd') throw new VirtualBonesError(`${name}: KTXorientation ${JSON.stringify(orientation)} is not "rd"`);
  const entry = container.keyValue['vbusd.layout'];
  if (!entry) throw new VirtualBonesError(`${name}: no vbusd.layout key/value entry: not a Virtual Bones texture`);
  let layout;
  try {
    layout = JSON.parse(text(entry));
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

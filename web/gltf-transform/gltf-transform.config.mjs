/**
 * gltf-transform CLI configuration that keeps Virtual Bones runtime packages working:
 *
 *   npm ci                                   # in web/gltf-transform
 *   npx gltf-transform --config web/gltf-transform/gltf-transform.config.mjs \
 *       optimize crowd.glb out.glb [--compress draco]
 *
 * It registers VBUSD_virtual_bones beside every extension the CLI knows (a config's
 * `extensions` replaces the CLI's list, so ALL_EXTENSIONS is repeated here), and adds three
 * commands under "User": `vbusd-meshopt` (meshopt compression that leaves POSITION and the skin
 * exact; `optimize --compress meshopt` and `quantize` are refused for a package, with an error
 * saying so), `vbusd-decompress` (writes a compressed package uncompressed, as vbusd's own readers
 * take it) and `vbusd-instance-defaults` (completes the crowd batches `instance` makes).
 */
import { ALL_EXTENSIONS, EXTMeshoptCompression } from '@gltf-transform/extensions';
import { MeshoptEncoder } from 'meshoptimizer';

import { VBUSDVirtualBones, vbusdInstanceDefaults, vbusdMeshopt } from './src/index.mjs';

// `gltf-transform --config PATH COMMAND ...` (the order this package documents): the CLI imports
// this file from `--config` wherever it stands, before it parses the command line, but its parser
// (gltf-transform 4.5) takes options only after the command and stops with "Unknown command
// --config". Moving the pair to the end of process.argv here, before the parse, makes both orders work.
const configAt = process.argv.indexOf('--config');
if (configAt >= 2 && configAt + 2 < process.argv.length && process.argv[configAt + 2] && !process.argv[configAt + 2].startsWith('-')) {
  process.argv.push(...process.argv.splice(configAt, 2));
}
// `optimize` compresses with meshopt unless told otherwise, and meshopt quantizes POSITION into the
// node transform, which Virtual Bones cannot skin (the extension refuses it). With this config a
// plain `optimize` therefore runs every other step and leaves the geometry uncompressed, saying so;
// `--compress draco` (lossy, within 2^-10 of the character's size) or `vbusd-meshopt` compress.
if (process.argv.slice(2).find((word) => !word.startsWith('-')) === 'optimize'
    && !process.argv.some((word) => word === '--compress' || word.startsWith('--compress='))) {
  process.argv.push('--compress', 'false');
  process.stderr.write('vbusd: optimize without --compress leaves the geometry uncompressed here (meshopt would quantize '
    + 'the positions Virtual Bones skin); use --compress draco or the vbusd-meshopt command to compress\n');
}

// What `vbusd-decompress` removes: the geometry compressions glTF-Transform decodes on read.
const COMPRESSION = ['KHR_draco_mesh_compression', 'EXT_meshopt_compression', 'KHR_meshopt_compression'];

export default {
  extensions: [...ALL_EXTENSIONS, VBUSDVirtualBones],
  onProgramReady: ({ program, io, Session }) => {
    program
      .command('vbusd-meshopt', 'Meshopt compression for VBUSD_virtual_bones packages (POSITION and skin exact)')
      .help('Reorders for locality, quantizes attributes Virtual Bones skinning does not read, and writes\nEXT_meshopt_compression (required). Load with a meshopt decoder (three.js: GLTFLoader.setMeshoptDecoder).')
      .argument('<input>', 'Path to read glTF 2.0 (.glb, .gltf) model')
      .argument('<output>', 'Path to write output')
      .option('--level <level>', 'Compression level: "high" (filters) or "medium"', { validator: ['high', 'medium'], default: 'high' })
      .action(async ({ args, options, logger }) => {
        await MeshoptEncoder.ready;
        return Session.create(io, logger, args.input, args.output)
          .transform(vbusdMeshopt({ encoder: MeshoptEncoder, extension: EXTMeshoptCompression, level: options.level }));
      });
    program
      .command('vbusd-decompress', 'Write a package without Draco or meshopt compression, as vbusd validate, info and view read it')
      .help('Reads the input with its compression decoded (KHR_draco_mesh_compression, EXT_meshopt_compression)\nand writes it with neither: what vbusd\'s readers and its viewer\'s page load.')
      .argument('<input>', 'Path to read glTF 2.0 (.glb, .gltf) model')
      .argument('<output>', 'Path to write output')
      .action(({ args, logger }) => Session.create(io, logger, args.input, args.output).transform((document) => {
        for (const extension of document.getRoot().listExtensionsUsed()) {
          if (COMPRESSION.includes(extension.extensionName)) extension.dispose();
        }
      }));
    program
      .command('vbusd-instance-defaults', 'Give GPU-instancing batches of Virtual Bones meshes their _VB_ instance attributes')
      .argument('<input>', 'Path to read glTF 2.0 (.glb, .gltf) model')
      .argument('<output>', 'Path to write output')
      .action(({ args, logger }) => Session.create(io, logger, args.input, args.output).transform(vbusdInstanceDefaults()));
  },
};

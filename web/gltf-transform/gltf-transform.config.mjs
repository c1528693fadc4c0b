/**
 * gltf-transform CLI configuration that keeps Virtual Bones runtime packages working:
 *
 *   npm ci                                   # in web/gltf-transform
 *   npx gltf-transform --config web/gltf-transform/gltf-transform.config.mjs \
 *       optimize crowd.glb out.glb --compress draco
 *
 * It registers VBUSD_virtual_bones beside every extension the CLI knows (a config's
 * `extensions` replaces the CLI's list, so ALL_EXTENSIONS is repeated here), and adds two
 * commands under "User": `vbusd-meshopt` (meshopt compression that leaves POSITION and the skin
 * exact; `optimize --compress meshopt` and `quantize` are refused for a package, with an error
 * saying so) and `vbusd-instance-defaults` (completes the crowd batches `instance` makes).
 */
import { ALL_EXTENSIONS, EXTMeshoptCompression } from '@gltf-transform/extensions';
import { MeshoptEncoder } from 'meshoptimizer';

import { VBUSDVirtualBones, vbusdInstanceDefaults, vbusdMeshopt } from './src/index.mjs';

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
      .command('vbusd-instance-defaults', 'Give GPU-instancing batches of Virtual Bones meshes their _VB_ instance attributes')
      .argument('<input>', 'Path to read glTF 2.0 (.glb, .gltf) model')
      .argument('<output>', 'Path to write output')
      .action(({ args, logger }) => Session.create(io, logger, args.input, args.output).transform(vbusdInstanceDefaults()));
  },
};

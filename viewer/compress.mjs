// Meshopt compression of glb files in place, keeping EXT_mesh_features / EXT_structural_metadata
// (glTF-Transform 4.5 registers both): vertex order optimised (meshopt reorder), positions, normals, texture
// coordinates and colours quantized (KHR_mesh_quantization; positions 16 bits over each mesh's bounds),
// feature ids left exact, then EXT_meshopt_compression (method QUANTIZE).
// usage: node compress.mjs meshopt FILE.glb...   prints one JSON line {file: [bytes before, bytes after]}
import { readFileSync, renameSync, writeFileSync } from 'node:fs';
import { Logger, NodeIO } from '@gltf-transform/core';
import { ALL_EXTENSIONS, EXTMeshoptCompression } from '@gltf-transform/extensions';
import { quantize, reorder } from '@gltf-transform/functions';
import { MeshoptDecoder, MeshoptEncoder } from 'meshoptimizer';

const [mode, ...files] = process.argv.slice(2);
if (mode !== 'meshopt' || files.length === 0) {
  process.stderr.write('usage: node compress.mjs meshopt FILE.glb...\n');
  process.exit(2);
}
await MeshoptEncoder.ready;
await MeshoptDecoder.ready;
const io = new NodeIO().setLogger(new Logger(Logger.Verbosity.ERROR)).registerExtensions(ALL_EXTENSIONS)
  .registerDependencies({ 'meshopt.encoder': MeshoptEncoder, 'meshopt.decoder': MeshoptDecoder });
const sizes = {};
for (const file of files) {
  const before = readFileSync(file).length;
  const doc = await io.read(file);
  await doc.transform(
    reorder({ encoder: MeshoptEncoder, target: 'size' }),
    quantize({ pattern: /^(POSITION|NORMAL|TEXCOORD_\d+|COLOR_\d+)$/, quantizePosition: 16, quantizeNormal: 10,
               quantizeTexcoord: 14, quantizeColor: 8, quantizationVolume: 'mesh' }),
  );
  doc.createExtension(EXTMeshoptCompression).setRequired(true)
    .setEncoderOptions({ method: EXTMeshoptCompression.EncoderMethod.QUANTIZE });
  const out = await io.writeBinary(doc);
  const tmp = `${file}.meshopt.tmp`;
  writeFileSync(tmp, out);
  renameSync(tmp, file);
  sizes[file] = [before, out.length];
}
process.stdout.write(JSON.stringify(sizes) + '\n');

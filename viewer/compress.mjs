// Compression of glb files in place through glTF-Transform 4.5, keeping EXT_mesh_features /
// EXT_structural_metadata (registered by @gltf-transform/extensions).
//   --geometry meshopt : vertex order optimised (meshopt reorder), positions (16 bits over each mesh's bounds),
//                        normals, texture coordinates and colours quantized (KHR_mesh_quantization), feature
//                        ids left exact, then EXT_meshopt_compression (method QUANTIZE)
//   --texture etc1s|uastc : every texture re-encoded as KTX2 / Basis Universal (KHR_texture_basisu) with
//                        mipmaps, through ktx2-encoder's Basis encoder (WebAssembly); JPEG / PNG decoded in JS
// usage: node compress.mjs [--geometry meshopt] [--texture etc1s|uastc] FILE.glb...
// prints, as its last line, one JSON object {file: [bytes before, bytes after]}
import { readFileSync, renameSync, writeFileSync } from 'node:fs';
import { Logger, NodeIO } from '@gltf-transform/core';
import { ALL_EXTENSIONS, EXTMeshoptCompression } from '@gltf-transform/extensions';
import { quantize, reorder } from '@gltf-transform/functions';
import { MeshoptDecoder, MeshoptEncoder } from 'meshoptimizer';

const args = process.argv.slice(2);
const opts = { geometry: 'none', texture: 'keep' };
const files = [];
for (let i = 0; i < args.length; i++) {
  if (args[i] === '--geometry' || args[i] === '--texture') opts[args[i].slice(2)] = args[++i];
  else files.push(args[i]);
}
if (!['none', 'meshopt'].includes(opts.geometry) || !['keep', 'etc1s', 'uastc'].includes(opts.texture) || !files.length) {
  process.stderr.write('usage: node compress.mjs [--geometry meshopt] [--texture etc1s|uastc] FILE.glb...\n');
  process.exit(2);
}

async function imageDecoder(buf) {  // JPEG / PNG -> RGBA for the Basis encoder
  const b = Buffer.from(buf);
  if (b[0] === 0xff && b[1] === 0xd8) {
    const { default: jpeg } = await import('jpeg-js');
    const d = jpeg.decode(b, { useTArray: true, formatAsRGBA: true, maxMemoryUsageInMB: 4096 });
    return { data: new Uint8Array(d.data), width: d.width, height: d.height };
  }
  const { PNG } = await import('pngjs');
  const p = PNG.sync.read(b);
  return { data: new Uint8Array(p.data), width: p.width, height: p.height };
}

await MeshoptEncoder.ready;
await MeshoptDecoder.ready;
const io = new NodeIO().setLogger(new Logger(Logger.Verbosity.ERROR)).registerExtensions(ALL_EXTENSIONS)
  .registerDependencies({ 'meshopt.encoder': MeshoptEncoder, 'meshopt.decoder': MeshoptDecoder });
const sizes = {};
for (const file of files) {
  const before = readFileSync(file).length;
  const doc = await io.read(file);
  if (opts.texture !== 'keep' && doc.getRoot().listTextures().length) {
    const { ktx2 } = await import('ktx2-encoder/gltf-transform');
    const log = console.log;
    console.log = () => {};  // the Basis encoder prints every slice
    try {
      await doc.transform(ktx2({ isUASTC: opts.texture === 'uastc', generateMipmap: true, imageDecoder }));
    } finally {
      console.log = log;
    }
  }
  if (opts.geometry === 'meshopt') {
    await doc.transform(
      reorder({ encoder: MeshoptEncoder, target: 'size' }),
      quantize({ pattern: /^(POSITION|NORMAL|TEXCOORD_\d+|COLOR_\d+)$/, quantizePosition: 16, quantizeNormal: 10,
                 quantizeTexcoord: 14, quantizeColor: 8, quantizationVolume: 'mesh' }),
    );
    doc.createExtension(EXTMeshoptCompression).setRequired(true)
      .setEncoderOptions({ method: EXTMeshoptCompression.EncoderMethod.QUANTIZE });
  }
  const out = await io.writeBinary(doc);
  const tmp = `${file}.compress.tmp`;
  writeFileSync(tmp, out);
  renameSync(tmp, file);
  sizes[file] = [before, out.length];
}
process.stdout.write('\n' + JSON.stringify(sizes) + '\n');

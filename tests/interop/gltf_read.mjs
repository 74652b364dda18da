// glTF Transform (npm @gltf-transform/core), a general glTF reader, on our files:
//   node gltf_read.mjs in.glb|in.gltf out.json [+ in out ...]
// writes every attribute of every POINTS primitive as plain arrays, plus the primitive's
// KHR_gaussian_splatting extension object read from the raw JSON. Several files are read in one
// process when their pairs are separated by "+".
import { readFileSync, writeFileSync } from 'node:fs';
import { join } from 'node:path';
import { createRequire } from 'node:module';
import { pathToFileURL } from 'node:url';

const require = createRequire(join(process.env.INTEROP_NODE_MODULES, 'index.js'));
const { NodeIO } = await import(pathToFileURL(require.resolve('@gltf-transform/core')));
const io = new NodeIO();

async function read(input, output) {
  const doc = await io.read(input);
  const out = { primitives: [] };
  for (const mesh of doc.getRoot().listMeshes()) {
    for (const prim of mesh.listPrimitives()) {
      if (prim.getMode() !== 0) continue;
      const attributes = {};
      for (const semantic of prim.listSemantics()) {
        const accessor = prim.getAttribute(semantic);
        const values = [];
        const element = [];
        for (let i = 0; i < accessor.getCount(); i++) values.push(Array.from(accessor.getElement(i, element)));
        attributes[semantic] = values;
      }
      out.primitives.push(attributes);
    }
  }
  // the extension object as written (glTF Transform keeps unknown extensions out of its model)
  const raw = input.endsWith('.glb') ? readFileSync(input).subarray(20, 20 + readFileSync(input).readUInt32LE(12))
                                     : readFileSync(input);
  const json = JSON.parse(new TextDecoder().decode(raw));
  out.extension = json.meshes[0].primitives[0].extensions.KHR_gaussian_splatting;
  out.extensionsUsed = json.extensionsUsed;
  writeFileSync(output, JSON.stringify(out));
}

const args = process.argv.slice(2);
while (args.length) {
  const end = args.indexOf('+') < 0 ? args.length : args.indexOf('+');
  await read(...args.splice(0, end + 1).filter(a => a !== '+'));
}

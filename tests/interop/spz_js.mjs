// spz-js (npm), a JavaScript port of Niantic's SPZ code with its own PLY and compressed PLY, on JSON
// arrays (its GaussianCloud: xyzw quaternions, SH coefficient-major with the channel fastest):
//   node spz_js.mjs read-spz|read-ply|read-compressed in out.json    (a file -> a GaussianCloud)
//   node spz_js.mjs write-spz|write-ply|write-compressed in.json out (a GaussianCloud -> a file)
// Several jobs run in one process when separated by "+".
import { createReadStream, readFileSync, writeFileSync } from 'node:fs';
import { join } from 'node:path';
import { Readable } from 'node:stream';
import { pathToFileURL } from 'node:url';

const lib = await import(pathToFileURL(join(process.env.INTEROP_NODE_MODULES, 'spz-js/dist/index.js')));
const FIELDS = ['positions', 'scales', 'rotations', 'alphas', 'colors', 'sh'];
const stream = path => Readable.toWeb(createReadStream(path));

function save(cloud, output) {
  if (!cloud) throw new Error('spz-js read nothing');
  const out = { numPoints: cloud.numPoints, shDegree: cloud.shDegree };
  // JSON has no infinity: an alpha byte of 0 or 255 decodes to an infinite logit
  for (const f of FIELDS) out[f] = Array.from(cloud[f], v => (Number.isFinite(v) ? v : Math.sign(v) * 3e38));
  writeFileSync(output, JSON.stringify(out));
}

function load(input) {
  const a = JSON.parse(readFileSync(input, 'utf8'));
  const cloud = { numPoints: a.numPoints, shDegree: a.shDegree, antialiased: false };
  for (const f of FIELDS) cloud[f] = new Float32Array(a[f].flat(Infinity));
  return cloud;
}

const VERBS = {
  'read-spz': async (input, output) => save(await lib.loadSpz(new Uint8Array(readFileSync(input))), output),
  'read-ply': async (input, output) => save(await lib.loadPly(stream(input)), output),
  'read-compressed': async (input, output) => save(await lib.loadCompressedPly(stream(input)), output),
  'write-spz': async (input, output) => writeFileSync(output, await lib.serializeSpz(load(input))),
  'write-ply': async (input, output) => writeFileSync(output, Buffer.from(lib.serializePly(load(input)))),
  'write-compressed': async (input, output) => writeFileSync(output, lib.serializeCompressedPly(load(input))),
};

const args = process.argv.slice(2);
while (args.length) {
  const end = args.indexOf('+') < 0 ? args.length : args.indexOf('+');
  const [verb, ...rest] = args.splice(0, end + 1).filter(a => a !== '+');
  if (!VERBS[verb]) throw new Error(`unknown verb ${verb}`);
  await VERBS[verb](...rest);
}

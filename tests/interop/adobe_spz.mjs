// Niantic's SPZ library (npm @adobe/spz, compiled to WebAssembly) on JSON arrays:
//   node adobe_spz.mjs write in.json out.spz VERSION   (a GaussianCloud in RDF axes -> SPZ)
//   node adobe_spz.mjs read in.spz out.json             (SPZ -> a GaussianCloud in RDF axes)
import { readFileSync, writeFileSync } from 'node:fs';
import { join } from 'node:path';
import { pathToFileURL } from 'node:url';

const lib = join(process.env.INTEROP_NODE_MODULES, '@adobe/spz/dist/spz.js');
const createSpzModule = (await import(pathToFileURL(lib))).default;
const spz = await createSpzModule({ print: () => {}, printErr: () => {} });
const [verb, input, output, version] = process.argv.slice(2);
const FIELDS = ['positions', 'scales', 'rotations', 'alphas', 'colors', 'sh'];

if (verb === 'write') {
  const a = JSON.parse(readFileSync(input, 'utf8'));
  const cloud = { numPoints: a.numPoints, shDegree: a.shDegree, antialiased: false, extensions: [] };
  for (const f of FIELDS) cloud[f] = new Float32Array(a[f].flat(Infinity));
  const bytes = spz.saveSpzToBuffer(cloud, { version: Number(version), from: spz.CoordinateSystem.RDF,
                                             sh1Bits: 5, shRestBits: 4 });
  if (!bytes.length) throw new Error('saveSpzToBuffer failed');
  writeFileSync(output, bytes);
} else if (verb === 'read') {
  const cloud = spz.loadSpzFromBuffer(new Uint8Array(readFileSync(input)), { to: spz.CoordinateSystem.RDF });
  if (!cloud || cloud.numPoints === undefined) throw new Error('loadSpzFromBuffer failed');
  const out = { numPoints: cloud.numPoints, shDegree: cloud.shDegree };
  // JSON has no infinity: an alpha byte of 0 or 255 decodes to an infinite logit
  for (const f of FIELDS) out[f] = Array.from(cloud[f], v => (Number.isFinite(v) ? v : Math.sign(v) * 3e38));
  writeFileSync(output, JSON.stringify(out));
} else {
  throw new Error(`unknown verb ${verb}`);
}

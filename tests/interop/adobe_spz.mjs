// Niantic's SPZ library (npm @adobe/spz, compiled to WebAssembly) on JSON arrays:
//   node adobe_spz.mjs write in.json out.spz VERSION [AXES]   (a GaussianCloud in RDF axes -> SPZ
//     stored in AXES, e.g. RUB or RFU, named by a coordinate-system record; by default RUB, recorded in v4)
//   node adobe_spz.mjs read in.spz out.json             (SPZ -> a GaussianCloud in RDF axes)
// Several jobs run in one process when separated by "+".
import { readFileSync, writeFileSync } from 'node:fs';
import { join } from 'node:path';
import { pathToFileURL } from 'node:url';

const lib = join(process.env.INTEROP_NODE_MODULES, '@adobe/spz/dist/spz.js');
const createSpzModule = (await import(pathToFileURL(lib))).default;
const spz = await createSpzModule({ print: () => {}, printErr: () => {} });
const FIELDS = ['positions', 'scales', 'rotations', 'alphas', 'colors', 'sh'];

// The library's bindings construct extension records as plain objects that saveSpzToBuffer refuses
// ("raw pointer to smart pointer"); one it loaded itself is accepted. So a one-splat v4 file carrying
// a coordinate-system record is loaded first (its five blocks stored as raw zstd blocks).
function coordinateRecord(axes) {
  const code = spz.CoordinateSystem[axes].value;
  const sizes = [9, 1, 3, 3, 4];
  const frames = sizes.map(n => Buffer.concat([Buffer.from([0x28, 0xb5, 0x2f, 0xfd, 0x20, n, (n << 3) | 1, 0, 0]),
                                               Buffer.alloc(n)]));
  const header = Buffer.alloc(32);
  header.writeUInt32LE(0x5053474e, 0);
  header.writeUInt32LE(4, 4);
  header.writeUInt32LE(1, 8);
  header.writeUInt8(12, 13);
  header.writeUInt8(0x2, 14);
  header.writeUInt8(sizes.length, 15);
  header.writeUInt32LE(44, 16);
  const record = Buffer.alloc(12);
  record.writeUInt32LE(0xadbe0003, 0);
  record.writeUInt32LE(4, 4);
  record.writeUInt32LE(code, 8);
  const toc = Buffer.alloc(16 * sizes.length);
  frames.forEach((f, i) => {
    toc.writeBigUInt64LE(BigInt(f.length), 16 * i);
    toc.writeBigUInt64LE(BigInt(sizes[i]), 16 * i + 8);
  });
  const file = Buffer.concat([header, record, toc, ...frames]);
  const [loaded] = spz.loadSpzFromBuffer(new Uint8Array(file), { to: spz.CoordinateSystem.RUB }).extensions;
  if (!loaded || loaded.coordinateSystem?.value !== code) throw new Error('no coordinate-system record loaded');
  return loaded;
}

function run(verb, input, output, version, axesArg) {
  if (verb === 'write') {
    const a = JSON.parse(readFileSync(input, 'utf8'));
    const cloud = { numPoints: a.numPoints, shDegree: a.shDegree, antialiased: false, extensions: [] };
    // every v4 file names its axes in a coordinate-system record (Splatwright writes RUB by default)
    const axes = axesArg ?? (Number(version) >= 4 ? 'RUB' : null);
    if (axes) cloud.extensions.push(coordinateRecord(axes));
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
}

// several jobs run in one process when separated by "+"
const args = process.argv.slice(2);
while (args.length) {
  const end = args.indexOf('+') < 0 ? args.length : args.indexOf('+');
  run(...args.splice(0, end + 1).filter(a => a !== '+'));
}

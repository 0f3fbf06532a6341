// Reading numpy .npz files in the browser: the zip central directory, STORE or DEFLATE entries (inflated with
// DecompressionStream), and .npy headers (format 1.0-3.0, little-endian). Enough for svox/volrend trees.
import {ViewerError} from './gl.js';

const DTYPES = {
  '<f2': [Uint16Array, 2, 'f16'], '<f4': [Float32Array, 4], '<f8': [Float64Array, 8], '<i4': [Int32Array, 4],
  '<i8': [BigInt64Array, 8], '<u2': [Uint16Array, 2], '<u1': [Uint8Array, 1], '|u1': [Uint8Array, 1],
  '<u4': [Uint32Array, 4], '<u8': [BigUint64Array, 8],
};

async function inflateRaw(bytes) {
  if (typeof DecompressionStream === 'undefined') {
    throw new ViewerError('this browser lacks DecompressionStream; DEFLATE-compressed trees need a current browser');
  }
  const stream = new Blob([bytes]).stream().pipeThrough(new DecompressionStream('deflate-raw'));
  return new Uint8Array(await new Response(stream).arrayBuffer());
}

function zipEntries(buf, name) {
  const dv = new DataView(buf.buffer, buf.byteOffset, buf.byteLength);
  let eocd = -1;
  for (let i = buf.length - 22; i >= Math.max(0, buf.length - 22 - 65535); i--) {
    if (dv.getUint32(i, true) === 0x06054b50) { eocd = i; break; }
  }
  if (eocd < 0) throw new ViewerError(`${name}: not a zip archive (.npz); the file is truncated or not a tree`);
  let count = dv.getUint16(eocd + 10, true);
  let cdOffset = dv.getUint32(eocd + 16, true);
  if (cdOffset === 0xffffffff || count === 0xffff) {  // zip64 end-of-central-directory
    const loc = eocd - 20;
    if (loc < 0 || dv.getUint32(loc, true) !== 0x07064b50) throw new ViewerError(`${name}: broken zip64 directory`);
    const z64 = Number(dv.getBigUint64(loc + 8, true));
    count = Number(dv.getBigUint64(z64 + 32, true));
    cdOffset = Number(dv.getBigUint64(z64 + 48, true));
  }
  const entries = [];
  let p = cdOffset;
  for (let e = 0; e < count; e++) {
    if (dv.getUint32(p, true) !== 0x02014b50) throw new ViewerError(`${name}: corrupt zip central directory`);
    const method = dv.getUint16(p + 10, true);
    let csize = dv.getUint32(p + 20, true);
    let usize = dv.getUint32(p + 24, true);
    const nlen = dv.getUint16(p + 28, true);
    const xlen = dv.getUint16(p + 30, true);
    const clen = dv.getUint16(p + 32, true);
    let local = dv.getUint32(p + 42, true);
    const fname = new TextDecoder().decode(buf.subarray(p + 46, p + 46 + nlen));
    let x = p + 46 + nlen;
    const xend = x + xlen;
    while (x + 4 <= xend) {  // zip64 extra field: the sizes/offset that were 0xffffffff, in this order
      const id = dv.getUint16(x, true);
      const len = dv.getUint16(x + 2, true);
      if (id === 0x0001) {
        let q = x + 4;
        if (usize === 0xffffffff) { usize = Number(dv.getBigUint64(q, true)); q += 8; }
        if (csize === 0xffffffff) { csize = Number(dv.getBigUint64(q, true)); q += 8; }
        if (local === 0xffffffff) { local = Number(dv.getBigUint64(q, true)); q += 8; }
      }
      x += 4 + len;
    }
    entries.push({fname, method, csize, usize, local});
    p = xend + clen;
  }
  return entries.map((en) => {
    const lnlen = dv.getUint16(en.local + 26, true);
    const lxlen = dv.getUint16(en.local + 28, true);
    const start = en.local + 30 + lnlen + lxlen;
    if (start + en.csize > buf.length) throw new ViewerError(`${name}: ${en.fname} runs past the end of the file (truncated)`);
    return {...en, data: buf.subarray(start, start + en.csize)};
  });
}

function parseNpy(bytes, where) {
  const dv = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  if (bytes[0] !== 0x93 || String.fromCharCode(...bytes.subarray(1, 6)) !== 'NUMPY') {
    throw new ViewerError(`${where}: not a .npy array`);
  }
  const major = bytes[6];
  const hlen = major === 1 ? dv.getUint16(8, true) : dv.getUint32(8, true);
  const hstart = major === 1 ? 10 : 12;
  const header = new TextDecoder().decode(bytes.subarray(hstart, hstart + hlen));
  const descr = /'descr':\s*'([^']+)'/.exec(header)?.[1];
  const fortran = /'fortran_order':\s*True/.test(header);
  const shapeText = /'shape':\s*\(([^)]*)\)/.exec(header)?.[1] ?? '';
  const shape = shapeText.split(',').map((s) => s.trim()).filter((s) => s).map(Number);
  if (fortran) throw new ViewerError(`${where}: Fortran-ordered arrays are not supported`);
  const body = bytes.slice(hstart + hlen);  // copy: typed arrays need aligned offsets
  if (descr && descr.startsWith('<U')) {  // numpy unicode: UTF-32LE code points
    const n = parseInt(descr.slice(2), 10);
    const cps = new Uint32Array(body.buffer, 0, n * Math.max(1, shape.reduce((a, b) => a * b, 1)));
    return {descr, shape, value: String.fromCodePoint(...Array.from(cps).filter((c) => c))};
  }
  const spec = DTYPES[descr];
  if (!spec) throw new ViewerError(`${where}: dtype ${descr} is not one a PlenOctree file uses`);
  const [Arr, size, kind] = spec;
  const count = shape.reduce((a, b) => a * b, 1);
  if (body.byteLength < count * size) throw new ViewerError(`${where}: array data is truncated`);
  return {descr, shape, kind, data: new Arr(body.buffer, 0, count)};
}

export async function readNpz(bytes, name) {
  const out = {};
  for (const en of zipEntries(bytes, name)) {
    let data = en.data;
    if (en.method === 8) data = await inflateRaw(data);
    else if (en.method !== 0) throw new ViewerError(`${name}: ${en.fname} uses zip method ${en.method} (only STORE and DEFLATE)`);
    out[en.fname.replace(/\.npy$/, '')] = parseNpy(data, `${name}:${en.fname}`);
  }
  return out;
}

// IEEE half -> float for a whole array.
export function halfToFloat(src) {
  const out = new Float32Array(src.length);
  for (let i = 0; i < src.length; i++) {
    const h = src[i];
    const s = h & 0x8000 ? -1 : 1;
    const e = (h >> 10) & 0x1f;
    const f = h & 0x3ff;
    out[i] = e === 0 ? s * 5.960464477539063e-8 * f : e === 31 ? (f ? NaN : s * Infinity) : s * Math.pow(2, e - 15) * (1 + f / 1024);
  }
  return out;
}

export function asFloat(arr) {
  if (arr.kind === 'f16') return halfToFloat(arr.data);
  return Float32Array.from(arr.data, Number);
}

// A person model in the browser: reads the gateway's model files (models/webmodel.py: the
// glb, the rig file, one file per update), refuses anything malformed with a ModelError
// naming the file and the field, and prepares what the renderer uploads. Mirrors
// models/update.py (a version step), models/draworder.py (the draw order and the triangle
// groups) and receiver/render.py's area_volume (a region area's premultiplied volume).
//
// Volume of one region area (receiver/render.py): k layers L_j (h x w RGB, row 0 at v = v1),
// alpha a_j = opacity_j * mask / 255, the neutral texture B under each layer texel's centre
// (bilinear, edges replicated), stored premultiplied relative to B,
//     (d, a) = (a_j (L_j - B) / 255, a_j),
// padded with PAD texels of zeros on every side (more on the right and at the bottom, to
// multiples of PAD: models/draworder.py's padded), rows bottom first (OpenGL's t = v).

import { Rig } from "./rig.js";

export const MIP_LEVELS = 4;  // models/draworder.py
export const PAD = 1 << MIP_LEVELS;
const MAX_LAYERS = 64;  // models/fields.py
const MAX_SIDE = 4096;
const MAX_AREAS_DRAWN = 62;  // models/draworder.py MAX_AREAS

export class ModelError extends Error {
  constructor(message) {
    super(message);
    this.name = "ModelError";
  }
}

function fail(where, message) {
  throw new ModelError(`${where}: ${message}`);
}

async function fetchBytes(url, where) {
  let response;
  try {
    response = await fetch(url);
  } catch (error) {
    fail(where, `cannot fetch (${error.message})`);
  }
  if (!response.ok) fail(where, `HTTP ${response.status}`);
  return await response.arrayBuffer();
}

function isNumber(x) {
  return typeof x === "number" && Number.isFinite(x);
}

function isCount(x, low, high) {
  return Number.isInteger(x) && x >= low && x <= high;
}

// ---- the model (glb + rig) --------------------------------------------------------------

// message: the gateway's {"type": "model", sha256, glb, rig, bytes}; query: "?token=..." or "".
// -> the Model (version 0); ModelError when a file is missing or malformed.
export async function loadModel(message, query = "") {
  if (!message || typeof message.glb !== "string" || typeof message.rig !== "string")
    throw new ModelError("model message: expected the glb and rig URLs");
  const [glb, rig] = await Promise.all([fetchBytes(message.glb + query, message.glb),
                                        fetchBytes(message.rig + query, message.rig)]);
  return await modelFromBytes(glb, rig, message.sha256, message.glb, message.rig);
}

// The Model of a glb's and a rig file's bytes (ArrayBuffers); `glbName`, `rigName` name them
// in messages.
export async function modelFromBytes(glb, rig, sha256 = "", glbName = "model.glb",
                                     rigName = "model.rig") {
  const mesh = readGlb(glb, glbName);
  const rigFile = readRig(rig, rigName, mesh.positions.length / 3);
  const images = await Promise.all(mesh.images.map(
    (bytes, i) => decodePng(bytes, `${glbName}: images[${i}]`)));
  const texture = images[0];
  const regions = mesh.regions.map((meta, r) => {
    const areas = meta.areas.map((a, n) => {
      const where = `${glbName}: extras.facewire.regions[${r}].areas[${n}]`;
      const [h, w] = a.size;
      const pick = (index, field) => {
        const image = images[index];
        if (image.width !== w || image.height !== h)
          fail(where, `${field}: image ${index} is ${image.width} x ${image.height}, ` +
                      `the area's size is ${w} x ${h}`);
        return image;
      };
      return { uvRect: a.uv_rect, h, w,
               layers: a.layers.map((index, j) => pick(index, `layers[${j}]`).rgba),
               mask: grey(pick(a.mask, "mask").rgba) };
    });
    return makeRegion(meta.name, meta.opacity, meta.rest, areas, texture);
  });
  let rigObject;
  try {
    rigObject = new Rig(mesh.positions, rigFile);
  } catch (error) {
    fail(rigName, `cannot build the morph (${error.message})`);
  }
  return { sha256, serial: 0, positions: mesh.positions, uv: mesh.uv,
           triangles: mesh.triangles, texture, regions, rig: rigObject,
           framing: mesh.framing };
}

// The glb's mesh, its images' bytes and its extras, checked (models/webmodel.py).
function readGlb(buffer, where) {
  if (!(buffer instanceof ArrayBuffer) || buffer.byteLength < 28)
    fail(where, "not a glTF binary (too short)");
  const view = new DataView(buffer);
  if (view.getUint32(0, true) !== 0x46546c67) fail(where, "not a glTF binary (no glTF magic)");
  if (view.getUint32(4, true) !== 2) fail(where, "glTF version is not 2");
  if (view.getUint32(8, true) !== buffer.byteLength)
    fail(where, `header says ${view.getUint32(8, true)} bytes, the file has ` +
                `${buffer.byteLength} (truncated?)`);
  const jsonLength = view.getUint32(12, true);
  if (view.getUint32(16, true) !== 0x4e4f534a || 20 + jsonLength + 8 > buffer.byteLength)
    fail(where, "chunk 0: not a JSON chunk of the file's length");
  let doc;
  try {
    doc = JSON.parse(new TextDecoder("utf-8", { fatal: true })
      .decode(new Uint8Array(buffer, 20, jsonLength)));
  } catch (error) {
    fail(where, `JSON chunk: not JSON (${error.message})`);
  }
  const binStart = 28 + jsonLength;
  const binLength = view.getUint32(20 + jsonLength, true);
  if (view.getUint32(24 + jsonLength, true) !== 0x004e4942 ||
      binStart + binLength > buffer.byteLength)
    fail(where, "chunk 1: not a BIN chunk within the file");
  if (doc === null || typeof doc !== "object") fail(where, "JSON chunk: not an object");

  const viewBytes = (index, field) => {
    const v = (doc.bufferViews || [])[index];
    if (!v || v.buffer !== 0 || !isCount(v.byteLength, 0, binLength) ||
        !isCount(v.byteOffset || 0, 0, binLength - v.byteLength) ||
        (v.byteStride !== undefined))
      fail(where, `${field}: bufferView ${index} is missing or outside the BIN chunk`);
    return [binStart + (v.byteOffset || 0), v.byteLength];
  };
  const accessor = (index, field, componentType, type, width, Kind) => {
    const a = (doc.accessors || [])[index];
    if (!a || a.componentType !== componentType || a.type !== type || !isCount(a.count, 1, 1 << 26))
      fail(where, `${field}: expected accessor of ${type} ${componentType}`);
    const [start, length] = viewBytes(a.bufferView, field);
    const offset = start + (a.byteOffset || 0);
    const bytes = a.count * width * Kind.BYTES_PER_ELEMENT;
    if ((a.byteOffset || 0) + bytes > length) fail(where, `${field}: runs past its bufferView`);
    return new Kind(buffer.slice(offset, offset + bytes));
  };
  const primitive = doc.meshes?.[0]?.primitives?.[0];
  if (!primitive || !primitive.attributes) fail(where, "meshes[0].primitives[0]: missing");
  const positions = accessor(primitive.attributes.POSITION, "POSITION", 5126, "VEC3", 3,
                             Float32Array);
  const n = positions.length / 3;
  if (!positions.every(Number.isFinite)) fail(where, "POSITION: contains NaN or infinity");
  const uvDown = accessor(primitive.attributes.TEXCOORD_0, "TEXCOORD_0", 5126, "VEC2", 2,
                          Float32Array);
  if (uvDown.length !== 2 * n) fail(where, `TEXCOORD_0: ${uvDown.length / 2} elements, ` +
                                           `POSITION has ${n}`);
  const uv = new Float32Array(2 * n);  // facewire's v up
  for (let i = 0; i < n; i++) {
    uv[2 * i] = uvDown[2 * i];
    uv[2 * i + 1] = 1 - uvDown[2 * i + 1];
  }
  if (!uv.every(Number.isFinite)) fail(where, "TEXCOORD_0: contains NaN or infinity");
  const indexType = (doc.accessors || [])[primitive.indices]?.componentType;
  const triangles = indexType === 5123
    ? accessor(primitive.indices, "indices", 5123, "SCALAR", 1, Uint16Array)
    : accessor(primitive.indices, "indices", 5125, "SCALAR", 1, Uint32Array);
  if (triangles.length % 3) fail(where, `indices: ${triangles.length}, not a multiple of 3`);
  for (const index of triangles)
    if (index >= n) fail(where, `indices: vertex ${index} outside the ${n} vertices`);

  const images = (doc.images || []).map((image, i) => {
    if (image.mimeType !== "image/png") fail(where, `images[${i}]: not a PNG`);
    const [start, length] = viewBytes(image.bufferView, `images[${i}]`);
    return new Uint8Array(buffer, start, length);
  });
  if (!images.length) fail(where, "images: no neutral texture");
  const extras = doc.extras?.facewire;
  if (!extras || extras.format !== 1) fail(where, "extras.facewire: missing or not format 1");
  if (!Array.isArray(extras.regions) || extras.regions.length > 8)
    fail(where, "extras.facewire.regions: expected at most 8 regions");
  extras.regions.forEach((r, i) => checkRegion(r, `${where}: extras.facewire.regions[${i}]`,
                                               images.length));
  const f = extras.framing;
  if (!f || !Array.isArray(f.centre) || f.centre.length !== 3 || !f.centre.every(isNumber) ||
      !isNumber(f.field) || !isNumber(f.fov_deg))
    fail(where, "extras.facewire.framing: expected centre, field and fov_deg");
  return { positions, uv, triangles, images, regions: extras.regions, framing: f };
}

function checkRegion(r, where, nImages) {
  if (!r || typeof r.name !== "string") fail(where, "name: missing");
  if (!isCount(r.layers, 1, MAX_LAYERS)) fail(where, `layers: expected 1 to ${MAX_LAYERS}`);
  checkStates(r.opacity, r.rest, r.layers, where);
  if (!Array.isArray(r.areas) || r.areas.length < 1 || r.areas.length > 8)
    fail(where, "areas: expected 1 to 8 areas");
  r.areas.forEach((a, n) => {
    const at = `${where}.areas[${n}]`;
    const rect = a.uv_rect;
    if (!Array.isArray(rect) || rect.length !== 4 || !rect.every(isNumber) ||
        !(rect[0] < rect[2] && rect[1] < rect[3]))
      fail(at, "uv_rect: expected (u0, v0, u1, v1) with u0 < u1, v0 < v1");
    if (!Array.isArray(a.size) || a.size.length !== 2 ||
        !a.size.every((s) => isCount(s, 1, MAX_SIDE)))
      fail(at, `size: expected [h, w] in [1, ${MAX_SIDE}]`);
    if (!Array.isArray(a.layers) || a.layers.length !== r.layers ||
        !a.layers.every((i) => isCount(i, 1, nImages - 1)))
      fail(at, `layers: expected ${r.layers} image indices`);
    if (!isCount(a.mask, 1, nImages - 1)) fail(at, "mask: expected an image index");
  });
}

function checkStates(opacity, rest, k, where) {
  if (!Array.isArray(opacity) || opacity.length !== k ||
      !opacity.every((a) => isNumber(a) && a >= 0 && a <= 1))
    fail(where, `opacity: expected ${k} numbers in [0, 1]`);
  if (!isNumber(rest) || rest < 0 || rest > k - 1)
    fail(where, `rest: expected a number in [0, ${k - 1}]`);
}

// A PNG's pixels: {width, height, rgba: Uint8ClampedArray(height * width * 4), row 0 = top}.
async function decodePng(bytes, where) {
  let bitmap;
  try {
    bitmap = await createImageBitmap(new Blob([bytes], { type: "image/png" }),
                                     { colorSpaceConversion: "none", premultiplyAlpha: "none" });
  } catch (error) {
    fail(where, `not a PNG that decodes (${error.message})`);
  }
  const { width, height } = bitmap;
  const canvas = new OffscreenCanvas(width, height);
  const context = canvas.getContext("2d", { willReadFrequently: true });
  context.drawImage(bitmap, 0, 0);
  bitmap.close();
  return { width, height, rgba: context.getImageData(0, 0, width, height).data };
}

function grey(rgba) {
  const out = new Uint8Array(rgba.length / 4);
  for (let i = 0; i < out.length; i++) out[i] = rgba[4 * i];
  return out;
}

// ---- the rig file and the update file: models/webmodel.py's container --------------------

const DTYPES = { f8: Float64Array, f4: Float32Array, u4: Uint32Array };

function readContainer(buffer, magic, where) {
  if (!(buffer instanceof ArrayBuffer) || buffer.byteLength < 12) fail(where, "too short");
  const view = new DataView(buffer);
  const head = String.fromCharCode(...new Uint8Array(buffer, 0, 4));
  if (head !== magic) fail(where, `not a ${magic} file (magic ${JSON.stringify(head)})`);
  if (view.getUint32(4, true) !== 1) fail(where, "version: expected 1");
  const length = view.getUint32(8, true);
  if (12 + length > buffer.byteLength || (12 + length) % 8)
    fail(where, "header length: past the file's end or not aligned");
  let header;
  try {
    header = JSON.parse(new TextDecoder("utf-8", { fatal: true })
      .decode(new Uint8Array(buffer, 12, length)));
  } catch (error) {
    fail(where, `header: not JSON (${error.message})`);
  }
  if (header === null || typeof header !== "object") fail(where, "header: not an object");
  const body = 12 + length;
  const arrays = {};
  for (const [name, spec] of Object.entries(header.arrays || {})) {
    const Kind = DTYPES[spec?.dtype];
    if (!Kind || !Array.isArray(spec.shape) || !spec.shape.every((s) => isCount(s, 0, 1 << 26)) ||
        !isCount(spec.offset, 0, buffer.byteLength) || spec.offset % 8)
      fail(where, `arrays.${name}: expected dtype, shape and an aligned offset`);
    const count = spec.shape.reduce((a, b) => a * b, 1);
    if (body + spec.offset + count * Kind.BYTES_PER_ELEMENT > buffer.byteLength)
      fail(where, `arrays.${name}: runs past the file's end (truncated?)`);
    const array = new Kind(buffer, body + spec.offset, count);
    if (Kind !== Uint32Array && !array.every(Number.isFinite))
      fail(where, `arrays.${name}: contains NaN or infinity`);
    arrays[name] = { array, shape: spec.shape };
  }
  return { header, arrays, body };
}

function readRig(buffer, where, n) {
  const { header, arrays } = readContainer(buffer, "FWRG", where);
  const get = (name, shape) => {
    const a = arrays[name];
    if (!a || a.shape.length !== shape.length ||
        !shape.every((s, i) => s === null || s === a.shape[i]))
      fail(where, `${name}: expected shape (${shape.map((s) => s ?? "*").join(", ")}), got ` +
                  `(${a ? a.shape.join(", ") : "none"})`);
    return a.array;
  };
  if (header.kernel !== "multiquadric" && header.kernel !== "gaussian")
    fail(where, `kernel: ${JSON.stringify(header.kernel)} is not a kernel`);
  if (header.vertices !== n) fail(where, `vertices: ${header.vertices}, the mesh has ${n}`);
  if (!isNumber(header.scale) || !(header.scale > 0) || !isNumber(header.balance))
    fail(where, "scale, balance: expected finite numbers");
  const centres = get("centres", [null, 3]);
  const m = centres.length / 3;
  const out = {
    centres, shape: get("shape", [m]), origin: get("origin", [3]),
    z: get("z", [m + (header.kernel === "multiquadric" ? 4 : 0), 9]),
    tangents: get("tangents", [9, 2, 3]), frozen: get("frozen", [null]),
    lip_vertices: get("lip_vertices", [null]),
  };
  out.lip_drop = get("lip_drop", [out.lip_vertices.length]);
  for (const name of ["frozen", "lip_vertices"])
    if (out[name].some((v) => v >= n)) fail(where, `${name}: a vertex outside the ${n}`);
  return { header, arrays: out };
}

// ---- updates (models/update.py: one version step) ----------------------------------------

// message: the gateway's {"type": "update", serial, url, bytes}. -> a new Model, version
// message.serial; ModelError when the file is missing, malformed or does not fit `model`
// (which stays valid: nothing of it is changed).
export async function loadUpdate(model, message, query = "") {
  if (!message || typeof message.url !== "string" || !isCount(message.serial, 1, 65535))
    throw new ModelError("update message: expected a url and a serial in 1 .. 65535");
  const bytes = await fetchBytes(message.url + query, message.url);
  return await applyUpdate(model, bytes, message.serial, message.url);
}

// The Model one update file (ArrayBuffer) makes of `model`: version `serial`, which must be
// the next after the model's (models/update.py: update n applies to version n - 1).
export async function applyUpdate(model, buffer, serial, where = "update") {
  if (serial !== model.serial + 1)
    fail(where, `serial: update ${serial} applies to version ${serial - 1}, the model is ` +
                `version ${model.serial}`);
  const { header, body } = readContainer(buffer, "FWUP", where);
  if (header.format !== 1 || !Array.isArray(header.regions) || !Array.isArray(header.blobs))
    fail(where, "expected format 1 with regions and blobs");
  const blobs = header.blobs.map((b, i) => {
    if (!Array.isArray(b) || b.length !== 2 || !isCount(b[0], 0, buffer.byteLength) ||
        !isCount(b[1], 1, buffer.byteLength) || b[0] % 8 || body + b[0] + b[1] > buffer.byteLength)
      fail(where, `blobs[${i}]: outside the file`);
    return new Uint8Array(buffer, body + b[0], b[1]);
  });
  const texture = await patchedTexture(model.texture, header.texture, blobs, where);
  const regions = model.regions.slice();
  for (const [c, change] of header.regions.entries()) {
    const at = `${where}: regions[${c}]`;
    const old = model.regions[change?.index];
    if (!old) fail(at, `index: ${change?.index} is not a region of the model`);
    if (change.name !== old.name) fail(at, `name: ${JSON.stringify(change.name)}, region ` +
                                           `${change.index} is ${JSON.stringify(old.name)}`);
    const states = change.states;
    if (!Array.isArray(states) || states.length < 1 || states.length > MAX_LAYERS)
      fail(at, `states: expected 1 to ${MAX_LAYERS}`);
    checkStates(change.opacity, change.rest, states.length, at);
    const layers = old.areas.map(() => []);
    for (const [j, state] of states.entries()) {
      if (state && "from" in state) {
        if (!isCount(state.from, 0, old.layers - 1))
          fail(at, `states[${j}].from: ${state.from} is not one of the ${old.layers} states`);
        old.areas.forEach((area, n) => layers[n].push(area.layers[state.from]));
      } else if (Array.isArray(state?.images) && state.images.length === old.areas.length) {
        for (const [n, blob] of state.images.entries()) {
          if (!isCount(blob, 0, blobs.length - 1))
            fail(at, `states[${j}].images[${n}]: no blob ${blob}`);
          const image = await decodePng(blobs[blob], `${at}.states[${j}].images[${n}]`);
          const area = old.areas[n];
          if (image.width !== area.w || image.height !== area.h)
            fail(at, `states[${j}].images[${n}]: ${image.width} x ${image.height}, the ` +
                     `area is ${area.w} x ${area.h}`);
          layers[n].push(image.rgba);
        }
      } else {
        fail(at, `states[${j}]: expected {from} or ${old.areas.length} images`);
      }
    }
    const areas = old.areas.map((area, n) => ({ uvRect: area.uvRect, h: area.h, w: area.w,
                                                layers: layers[n], mask: area.mask }));
    regions[change.index] = makeRegion(old.name, change.opacity, change.rest, areas, texture);
  }
  return { ...model, serial, regions, texture };
}

// The texture an update's optional `texture` entry makes of `texture` (a patch,
// models/patch.py): [{rect: [row, col, h, w], image: blob}], each blob the PNG of the
// rectangle's new texels; the texture itself when there is no entry.
async function patchedTexture(texture, tiles, blobs, where) {
  if (tiles === undefined) return texture;
  if (!Array.isArray(tiles) || tiles.length < 1 || tiles.length > 64)
    fail(where, "texture: expected 1 to 64 tiles");
  const W = texture.width, H = texture.height, rgba = new Uint8ClampedArray(texture.rgba);
  for (const [t, tile] of tiles.entries()) {
    const at = `${where}: texture[${t}]`;
    const rect = tile?.rect;
    if (!Array.isArray(rect) || rect.length !== 4 || !isCount(rect[0], 0, H - 1) ||
        !isCount(rect[1], 0, W - 1) || !isCount(rect[2], 1, H - rect[0]) ||
        !isCount(rect[3], 1, W - rect[1]))
      fail(at, "rect: expected [row, col, h, w] inside the texture");
    if (!isCount(tile.image, 0, blobs.length - 1)) fail(at, `image: no blob ${tile.image}`);
    const image = await decodePng(blobs[tile.image], `${at}.image`);
    const [row, col, h, w] = rect;
    if (image.width !== w || image.height !== h)
      fail(at, `image: ${image.width} x ${image.height}, the rect is ${w} x ${h}`);
    for (let y = 0; y < h; y++)
      rgba.set(image.rgba.subarray(4 * y * w, 4 * (y + 1) * w), 4 * ((row + y) * W + col));
  }
  return { width: W, height: H, rgba };
}

// ---- regions: volumes and draw order -----------------------------------------------------

function makeRegion(name, opacity, rest, areas, texture) {
  for (const area of areas) {
    area.volume = areaVolume(texture, area, opacity);
    area.padded = paddedRect(area);
  }
  return { name, opacity, rest, layers: opacity.length, areas };
}

// models/draworder.py padded: the smallest multiple of PAD holding n texels and PAD more on
// either side.
export function padded(n) {
  return Math.ceil((n + 2 * PAD) / PAD) * PAD;
}

function paddedRect(area) {
  const [u0, v0, u1, v1] = area.uvRect;
  const du = (u1 - u0) / area.w, dv = (v1 - v0) / area.h;
  return [u0 - PAD * du, v1 - (padded(area.h) - PAD) * dv, u0 + (padded(area.w) - PAD) * du,
          v1 + PAD * dv];
}

// receiver/render.py area_volume: {k, height, width, data: Float32Array(k * H' * W' * 4)}
// (d_r, d_g, d_b, a) per texel, rows bottom first.
function areaVolume(texture, area, opacity) {
  const k = opacity.length, h = area.h, w = area.w;
  const [u0, v0, u1, v1] = area.uvRect;
  const H = texture.height, W = texture.width, tex = texture.rgba;
  const under = new Float32Array(h * w * 3);
  for (let y = 0; y < h; y++) {
    const v = v1 - (y + 0.5) / h * (v1 - v0);
    const fy = (1 - v) * H - 0.5;
    const y0 = Math.floor(fy), wy = fy - y0;
    const ya = Math.min(Math.max(y0, 0), H - 1), yb = Math.min(Math.max(y0 + 1, 0), H - 1);
    for (let x = 0; x < w; x++) {
      const u = u0 + (x + 0.5) / w * (u1 - u0);
      const fx = u * W - 0.5;
      const x0 = Math.floor(fx), wx = fx - x0;
      const xa = Math.min(Math.max(x0, 0), W - 1), xb = Math.min(Math.max(x0 + 1, 0), W - 1);
      for (let c = 0; c < 3; c++) {
        const top = tex[4 * (ya * W + xa) + c] * (1 - wx) + tex[4 * (ya * W + xb) + c] * wx;
        const bottom = tex[4 * (yb * W + xa) + c] * (1 - wx) + tex[4 * (yb * W + xb) + c] * wx;
        under[3 * (y * w + x) + c] = top * (1 - wy) + bottom * wy;
      }
    }
  }
  const height = padded(h), width = padded(w);
  const data = new Float32Array(k * height * width * 4);
  for (let j = 0; j < k; j++) {
    const layer = area.layers[j], scale = opacity[j] / 255;
    for (let y = 0; y < h; y++) {
      const row = (j * height + (height - 1 - PAD - y)) * width + PAD;  // rows bottom first
      for (let x = 0; x < w; x++) {
        const i = y * w + x, o = 4 * (row + x);
        const a = scale * area.mask[i];
        data[o] = a * (layer[4 * i] - under[3 * i]) / 255;
        data[o + 1] = a * (layer[4 * i + 1] - under[3 * i + 1]) / 255;
        data[o + 2] = a * (layer[4 * i + 2] - under[3 * i + 2]) / 255;
        data[o + 3] = a;
      }
    }
  }
  return { k, height, width, data };
}

// models/draworder.py region_areas: [{region index, area}], opaque regions first, then those
// with a transparent state, each set in packet order.
export function regionAreas(model) {
  const opaque = [], rest = [];
  model.regions.forEach((r, i) => (Math.min(...r.opacity) >= 1 ? opaque : rest).push(i));
  return [...opaque, ...rest].flatMap((i) => model.regions[i].areas.map(
    (area) => ({ region: i, area })));
}

// models/draworder.py triangle_groups: the triangles sorted by the set of areas their UV box
// meets (stable), and per group {mask (array of area indices), first, count} in triangles.
export function triangleGroups(model, areas) {
  if (areas.length > MAX_AREAS_DRAWN) throw new ModelError(`${areas.length} region areas, ` +
                                                           `at most ${MAX_AREAS_DRAWN}`);
  const t = model.triangles, uv = model.uv, m = t.length / 3;
  const masks = new Array(m);
  for (let i = 0; i < m; i++) {
    let lu = Infinity, lv = Infinity, hu = -Infinity, hv = -Infinity;
    for (let c = 0; c < 3; c++) {
      const u = uv[2 * t[3 * i + c]], v = uv[2 * t[3 * i + c] + 1];
      lu = Math.min(lu, u); hu = Math.max(hu, u); lv = Math.min(lv, v); hv = Math.max(hv, v);
    }
    let mask = 0n;
    areas.forEach(({ area }, a) => {
      const [u0, v0, u1, v1] = area.padded;
      if (hu >= u0 && lu <= u1 && hv >= v0 && lv <= v1) mask |= 1n << BigInt(a);
    });
    masks[i] = mask;
  }
  const order = [...Array(m).keys()].sort((a, b) => (masks[a] < masks[b] ? -1 :
    masks[a] > masks[b] ? 1 : a - b));
  const sorted = new Uint32Array(3 * m);
  const groups = [];
  order.forEach((tri, i) => {
    sorted.set(t.subarray(3 * tri, 3 * tri + 3), 3 * i);
    const last = groups[groups.length - 1];
    if (last && last.key === masks[tri]) last.count++;
    else groups.push({ key: masks[tri], first: i, count: 1 });
  });
  for (const g of groups)
    g.areas = areas.map((_, a) => a).filter((a) => (g.key >> BigInt(a)) & 1n);
  return { triangles: sorted, groups };
}

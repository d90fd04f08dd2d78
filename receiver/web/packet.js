/**
 * The frame packet, protocol version 2, decoded in the browser: it mirrors
 * protocol/packet.py (docs/DESIGN.md section 3), which defines the layout once; the tests
 * (tests/test_webpage.py) check this module's table against ``protocol.packet.QUANTISERS`` and
 * its decoding against Python's on real and corrupt packets.
 *
 * 43 bytes: the fields packed most significant bit first into one 328-bit stream (version 4
 * bits, flags 8, seq 16, serial 11, then the quantised codes of QUANTISERS in order), then a
 * CRC-16/CCITT-FALSE (polynomial 0x1021, initial 0xFFFF, no reflection, no final XOR) of
 * bytes 0..40, stored big-endian in bytes 41..42. A code k of a quantiser decodes to
 * ``lo + k * step``; rotation is degrees on the wire and radians here. Decoding either returns a
 * frame or throws PacketError with a reason, checked in this order: "size" (not 43 bytes),
 * "version" (top nibble of byte 0 not 2), "crc", "reserved" (flag bit 6 or 7 set).
 */

export const VERSION = 2;
export const PACKET_BYTES = 43;
export const N_RESIDUAL_POINTS = 9;
export const N_REGIONS = 8;
export const N_SHADE = 3;
export const SEQ_MODULO = 1 << 16;
export const SERIAL_BITS = 11;
export const MAX_SERIAL = (1 << SERIAL_BITS) - 1;

/** Per-frame state bits (``protocol.packet.Flag``). */
export const Flag = Object.freeze({
  FACE_PRESENT: 1 << 0,
  TRACKING_LOST: 1 << 1,
  CLAMPED: 1 << 2,
  HELD: 1 << 3,
  MIRRORED: 1 << 4,
  REACQUIRED: 1 << 5,
});
export const RESERVED_FLAGS = 0xff & ~Object.values(Flag).reduce((a, b) => a | b, 0);

/** The quantisers in stream order: code k of ``bits`` bits decodes to ``lo + k * step``. */
export const QUANTISERS = Object.freeze([
  {name: "rotation", count: 3, bits: 11, lo: -102.4, step: 0.1, unit: "degree"},
  {name: "shift_xy", count: 2, bits: 12, lo: -1024.0, step: 0.5, unit: "mm"},
  {name: "shift_z", count: 1, bits: 11, lo: -2147.0, step: 1.0, unit: "mm"},
  {name: "residuals", count: 2 * N_RESIDUAL_POINTS, bits: 8, lo: -32.0, step: 0.25, unit: "mm"},
  {name: "q", count: N_REGIONS, bits: 7, lo: 0.0, step: 1.0 / 16.0, unit: "layer"},
  {name: "shade", count: N_SHADE, bits: 7, lo: -1.0, step: 1.0 / 64.0, unit: "ln gain"},
].map(Object.freeze));

const BODY_BYTES = PACKET_BYTES - 2;
const DEG = Math.PI / 180.0; // numpy's radians(): x * (pi / 180)

/** The slots of the stream in order: {start bit, width, lo, step} (lo and step of quantised
 * slots only). */
const SLOTS = (() => {
  const slots = [];
  let start = 0;
  const add = (width, lo = null, step = null) => {
    slots.push({start, width, lo, step});
    start += width;
  };
  add(4); // version
  add(8); // flags
  add(16); // seq
  add(SERIAL_BITS); // serial
  for (const q of QUANTISERS) {
    for (let i = 0; i < q.count; i++) add(q.bits, q.lo, q.step);
  }
  if (start !== 8 * BODY_BYTES) throw new Error(`packet layout: ${start} bits, not ${8 * BODY_BYTES}`);
  return slots;
})();
const QUANTISED = 4; // the first quantised slot

const CRC_TABLE = (() => {
  const table = new Uint16Array(256);
  for (let byte = 0; byte < 256; byte++) {
    let crc = byte << 8;
    for (let i = 0; i < 8; i++) crc = crc & 0x8000 ? ((crc << 1) ^ 0x1021) & 0xffff : (crc << 1) & 0xffff;
    table[byte] = crc;
  }
  return table;
})();

/** CRC-16/CCITT-FALSE of ``bytes`` (a Uint8Array), like ``binascii.crc_hqx(bytes, 0xFFFF)``. */
export function crc16(bytes) {
  let crc = 0xffff;
  for (let i = 0; i < bytes.length; i++) crc = ((crc << 8) & 0xffff) ^ CRC_TABLE[((crc >> 8) ^ bytes[i]) & 0xff];
  return crc;
}

/** A byte string that is not a valid packet; ``reason`` is "size", "version", "crc" or
 * "reserved" (``protocol.packet.PacketError``). */
export class PacketError extends Error {
  constructor(reason, message) {
    super(message);
    this.name = "PacketError";
    this.reason = reason;
  }
}

/** The quantisers as plain data, as the Hello carries them (``protocol.packet.quantiser_table``). */
export function quantiserTable() {
  return QUANTISERS.map(({name, count, bits, lo, step, unit}) => ({name, count, bits, lo, step, unit}));
}

/** Whether a Hello's ``quantisers`` are this module's table (the Python receiver refuses a
 * Hello whose table differs: ``protocol.control.Hello``). */
export function sameQuantisers(table) {
  const mine = quantiserTable();
  return Array.isArray(table) && table.length === mine.length && mine.every((q, i) => {
    const t = table[i];
    return t !== null && typeof t === "object" && Object.keys(t).length === Object.keys(q).length &&
      Object.entries(q).every(([key, value]) => t[key] === value);
  });
}

/** The code of the slot at ``start`` bits of ``width`` <= 16 bits: read from the 24-bit
 * big-endian word of bytes start/8 .. start/8 + 2 (at most byte 42). */
function slot(bytes, start, width) {
  const b = start >> 3;
  const word = (bytes[b] << 16) | (bytes[b + 1] << 8) | bytes[b + 2];
  return (word >> (24 - (start & 7) - width)) & ((1 << width) - 1);
}

/**
 * Decode one packet.
 *
 * @param {Uint8Array} bytes the packet.
 * @returns {{seq: number, flags: number, serial: number, rotation: Float32Array,
 *   translation: Float32Array, residuals: Float32Array, q: Float32Array, shade: Float32Array}}
 *   rotation (3) radians, model -> camera, as a rotation vector; translation (3) mm;
 *   residuals (18) = (9, 2) row-major, mm; q (8) layers; shade (3) ln gain; the values
 *   rounded to float32 as ``protocol.packet.decode`` gives them.
 * @throws {PacketError} wrong size, unknown version, bad CRC or reserved bits set.
 */
export function decode(bytes) {
  if (bytes.length !== PACKET_BYTES) {
    throw new PacketError("size", `packet has ${bytes.length} bytes, expected ${PACKET_BYTES}`);
  }
  if (bytes[0] >> 4 !== VERSION) {
    throw new PacketError("version", `packet version ${bytes[0] >> 4}, expected ${VERSION}`);
  }
  if (crc16(bytes.subarray(0, BODY_BYTES)) !== ((bytes[BODY_BYTES] << 8) | bytes[BODY_BYTES + 1])) {
    throw new PacketError("crc", "packet CRC mismatch");
  }
  const flags = slot(bytes, SLOTS[1].start, SLOTS[1].width);
  if (flags & RESERVED_FLAGS) throw new PacketError("reserved", "packet rejected: reserved bits set");
  const value = new Float64Array(SLOTS.length - QUANTISED);
  for (let i = QUANTISED; i < SLOTS.length; i++) {
    const s = SLOTS[i];
    value[i - QUANTISED] = s.lo + slot(bytes, s.start, s.width) * s.step;
  }
  return {
    seq: slot(bytes, SLOTS[2].start, SLOTS[2].width),
    flags,
    serial: slot(bytes, SLOTS[3].start, SLOTS[3].width),
    rotation: Float32Array.from(value.subarray(0, 3), (x) => x * DEG),
    translation: Float32Array.from(value.subarray(3, 6)),
    residuals: Float32Array.from(value.subarray(6, 6 + 2 * N_RESIDUAL_POINTS)),
    q: Float32Array.from(value.subarray(6 + 2 * N_RESIDUAL_POINTS, 6 + 2 * N_RESIDUAL_POINTS + N_REGIONS)),
    shade: Float32Array.from(value.subarray(6 + 2 * N_RESIDUAL_POINTS + N_REGIONS)),
  };
}

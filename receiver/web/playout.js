/**
 * The playout buffer and loss concealment of the page: it mirrors receiver/playout.py, whose
 * module docstring is the definition (slots and sequence numbers, depth, the jitter-adaptive
 * deadline ``due``, duplicates, late, far and stray packets, restart and resync, the skip
 * rule, hold then smoothstep ease toward the model's rest, face lost). The tests
 * (tests/test_webpage.py) drive this class and ``receiver.playout.replay_states`` with the
 * same packets and arrival times and compare every state and count.
 *
 * In short: ``push(bytes, arrival_s)`` takes any packet as it arrives; ``pop()`` returns the
 * next output frame's FrameState, one slot after another in sequence order, concealing a
 * missing slot (pose held; expression weight held for HOLD_S from the last face-present slot,
 * then eased as ``1 - (3 p^2 - 2 p^3)``, ``p = t / EASE_S``, to zero residuals and the rest Q).
 * ``ready`` says the next pop plays a packet already in; ``due()`` the arrival-clock time after
 * which a missing slot is concealed: ``min(o') + n / rate + margin``, o' the offsets of the
 * last BASE_PACKETS packets (playout.py).
 *
 * A FrameState is a plain object with the Python names: seq (number | null), rotation
 * (Float64Array(9), 3x3 row-major, model -> camera), translation (Float64Array(3), mm),
 * residuals (Float32Array(18), (9, 2) row-major, mm, tangent frames), q (Float32Array(8),
 * layers), flags, status (one of STATUSES), weight, arrival_s (number | null), serial,
 * shade (Float32Array(3), ln gain). Its arrays are shared between states: read, never write.
 */

import {N_REGIONS, N_SHADE, N_RESIDUAL_POINTS, PACKET_BYTES, SEQ_MODULO, Flag, PacketError, decode} from "./packet.js";

export const DEFAULT_DEPTH = 3;
export const HOLD_S = 0.2;
export const EASE_S = 0.5;
export const JUMP_S = 2.0;
export const JITTER_PACKETS = 64;
export const MIN_JITTER_PACKETS = 30; // a second at 30 Hz (playout.py)
export const GUARD_S = 0.005;
export const BASE_PACKETS = 8; // the deadline's base: the last quarter second at 30 Hz
export const MAX_DEPTH = 1024;
export const MIN_RATE_HZ = 1.0; // protocol/rate.py
export const MAX_RATE_HZ = 1000.0;
export const STATUSES = Object.freeze(["received", "held", "easing", "neutral", "face_lost"]);
const HALF = SEQ_MODULO / 2;
const EPS = 1e-9;
const COUNTS = ["received", "corrupt", "duplicate", "late", "stray", "discarded", "concealed", "skipped", "restarts"];

/** Signed distance from ``ref`` to ``seq`` on the 16-bit circle, in [-32768, 32767]. */
export function serialDistance(seq, ref) {
  const d = (seq - ref + HALF) % SEQ_MODULO;
  return (d < 0 ? d + SEQ_MODULO : d) - HALF;
}

/** Rodrigues' formula as ``models.geometry.rotation_matrix`` (OpenCV's Rodrigues):
 * (3,) rotation vector, radians -> Float64Array(9), 3x3 row-major. */
export function rotationMatrix(r) {
  const [x, y, z] = [r[0], r[1], r[2]];
  const theta = Math.hypot(x, y, z);
  if (theta < Number.EPSILON) return Float64Array.of(1, 0, 0, 0, 1, 0, 0, 0, 1);
  const c = Math.cos(theta), s = Math.sin(theta), c1 = 1 - c;
  const [a, b, e] = [x / theta, y / theta, z / theta];
  return Float64Array.of(
    c + c1 * a * a, c1 * a * b - s * e, c1 * a * e + s * b,
    c1 * a * b + s * e, c + c1 * b * b, c1 * b * e - s * a,
    c1 * a * e - s * b, c1 * b * e + s * a, c + c1 * e * e);
}

function sameBytes(a, b) {
  if (a.length !== b.length) return false;
  for (let i = 0; i < a.length; i++) if (a[i] !== b[i]) return false;
  return true;
}

function minKey(map) {
  let m = Infinity;
  for (const k of map.keys()) if (k < m) m = k;
  return m;
}

const ZERO_RESIDUALS = new Float32Array(2 * N_RESIDUAL_POINTS);
const ZERO_SHADE = new Float32Array(N_SHADE);
const DEFAULT_ROTATION = Float64Array.of(1, 0, 0, 0, 1, 0, 0, 0, 1);
const DEFAULT_TRANSLATION = Float64Array.of(0, 0, -600); // protocol.packet.Frame's default pose

/** The bytes of a packet as a Uint8Array copy, or null when ``data`` holds no bytes
 * (ArrayBuffer and typed arrays hold bytes; anything else counts as corrupt). */
function bytesOf(data) {
  if (data instanceof ArrayBuffer) return new Uint8Array(data.slice(0));
  if (ArrayBuffer.isView(data)) return new Uint8Array(data.buffer.slice(data.byteOffset, data.byteOffset + data.byteLength));
  return null;
}

/**
 * The playout buffer of one stream (``receiver.playout.Playout``).
 *
 * @param {number} rateHz the stream's rate (the Hello's), which is also the pop rate, [1, 1000].
 * @param {{depth?: number, holdS?: number, easeS?: number, restQ?: ArrayLike<number>|null,
 *   skip?: boolean}} options as Python's ``depth``, ``hold_s``, ``ease_s``, ``rest_q``, ``skip``.
 * @throws {RangeError} an argument out of range (naming it).
 */
export class Playout {
  constructor(rateHz, {depth = DEFAULT_DEPTH, holdS = HOLD_S, easeS = EASE_S, restQ = null, skip = true} = {}) {
    if (typeof rateHz !== "number" || !(rateHz >= MIN_RATE_HZ && rateHz <= MAX_RATE_HZ)) {
      throw new RangeError(`rate_hz: expected a number in [${MIN_RATE_HZ}, ${MAX_RATE_HZ}], got ${rateHz}`);
    }
    if (!Number.isInteger(depth) || depth < 1 || depth > MAX_DEPTH) {
      throw new RangeError(`depth: expected an integer in [1, ${MAX_DEPTH}], got ${depth}`);
    }
    for (const [name, value] of [["hold_s", holdS], ["ease_s", easeS]]) {
      if (typeof value !== "number" || !Number.isFinite(value) || value < 0) {
        throw new RangeError(`${name}: expected a finite number >= 0, got ${value}`);
      }
    }
    this.rateHz = rateHz;
    this.depth = depth;
    this.holdS = holdS;
    this.easeS = easeS;
    this.skip = Boolean(skip);
    this.window = Math.max(4 * depth, Math.ceil(JUMP_S * rateHz));
    this.restQ = restQ ?? new Float32Array(N_REGIONS);
    this._counts = Object.fromEntries(COUNTS.map((k) => [k, 0]));
    // stream
    this._started = false;
    this._playing = false;
    this._countdown = 0;
    this._ref = 0; // extended seq: the first packet's, then the playout point (_next)
    this._next = 0;
    this._newest = 0;
    this._buffer = new Map(); // extended seq -> packet
    this._seen = new Map(); // extended seq -> the packet's bytes
    this._candidate = null; // [packet, bytes]
    this._lateRun = 0;
    this._lateStart = 0.0;
    this._offsets = []; // a_i - e_i / rate_hz of the last JITTER_PACKETS packets
    // output
    this._rotation = DEFAULT_ROTATION;
    this._translation = DEFAULT_TRANSLATION;
    this._residuals = ZERO_RESIDUALS; // E, the last face-present expression
    this._q = this._restQ;
    this._serial = 0;
    this._shade = ZERO_SHADE;
    this._weight = 0.0;
    this._easing = true;
    this._since = 0; // slots since the last face-present slot
    this._easeBegin = 0.0;
  }

  /** Float32Array(8): each slot's Q on the neutral face; another model version's may be set. */
  get restQ() {
    return this._restQ;
  }

  set restQ(value) {
    const rest = Float32Array.from(value);
    if (rest.length !== N_REGIONS || !rest.every(Number.isFinite)) {
      throw new RangeError(`rest_q: expected ${N_REGIONS} finite values, got ${value}`);
    }
    this._restQ = rest;
  }

  /** The latency the buffer adds to an on-time packet on a tick clock, s. */
  get latencyS() {
    return this.depth / this.rateHz;
  }

  /** Counts so far: received, corrupt, duplicate, late, stray, discarded, concealed, skipped,
   * restarts (a copy). */
  get stats() {
    return {...this._counts};
  }

  /** True when the next pop plays a buffered packet, or counts down towards one. */
  get ready() {
    return this._buffer.size > 0 && (!this._playing || this._buffer.has(this._next));
  }

  /** Slots from the playout point to the newest buffered packet, both counted; 0 when empty. */
  get ahead() {
    if (this._buffer.size === 0) return 0;
    return this._newest - (this._playing ? this._next : minKey(this._buffer)) + 1;
  }

  /** How long after its earliest expected arrival a missing slot waits, s. */
  get marginS() {
    const period = 1.0 / this.rateHz;
    if (this._offsets.length < MIN_JITTER_PACKETS) return this.depth * period;
    const spread = Math.max(...this._offsets) - Math.min(...this._offsets);
    return Math.min(period + spread + GUARD_S, this.depth * period);
  }

  /** The arrival-clock time after which the next slot is concealed if its packet has not
   * come; null when nothing plays yet. */
  due() {
    if (!this._playing || this._offsets.length === 0) return null;
    const base = Math.min(...this._offsets.slice(-BASE_PACKETS)); // min(o')
    return base + this._next / this.rateHz + this.marginS;
  }

  /** True when no buffered packet waits to be played. */
  get drained() {
    return this._buffer.size === 0 && (this._playing || !this._started);
  }

  /**
   * Take one packet as it arrives; never throws on its content.
   *
   * @param {*} data the packet: an ArrayBuffer or a typed array (anything else is corrupt).
   * @param {number} arrivalS its arrival time, s, on one monotonic clock.
   * @returns {string|null} null for a packet that decodes (counted ``received``), else why it is
   *   corrupt: a ``PacketError`` reason, or "type" for data that holds no bytes (Python counts
   *   only ``corrupt``; the page shows the reasons).
   * @throws {RangeError} arrivalS is not a finite number.
   */
  push(data, arrivalS) {
    if (typeof arrivalS !== "number" || !Number.isFinite(arrivalS)) {
      throw new RangeError(`arrival_s: expected a finite number, got ${arrivalS}`);
    }
    const [packet, raw, reason] = Playout._decode(data, arrivalS);
    if (packet === null) {
      this._counts.corrupt += 1;
      return reason;
    }
    this._counts.received += 1;
    if (!this._started) {
      this._restart([[packet, raw]], false);
      return null;
    }
    const d = serialDistance(packet.seq, ((this._ref % SEQ_MODULO) + SEQ_MODULO) % SEQ_MODULO);
    if (d < -this.window || d >= this.window) {
      this._far(packet, raw);
      return null;
    }
    if (this._candidate !== null) {
      this._counts.stray += 1;
      this._candidate = null;
    }
    const ext = this._ref + d;
    const behind = this._playing && ext < this._next;
    if (this._seen.has(ext) && (!behind || sameBytes(this._seen.get(ext), raw))) {
      this._counts.duplicate += 1;
      return null;
    }
    this._seen.set(ext, raw);
    this._offset(packet.arrival_s - ext / this.rateHz);
    if (behind) {
      this._late(packet, raw);
      return null;
    }
    this._buffer.set(ext, packet);
    this._newest = Math.max(this._newest, ext);
    this._lateRun = 0;
    return null;
  }

  /** The FrameState of the next output frame (call once per frame at the stream's rate, or on
   * ``ready`` / after ``due()`` as the page does). */
  pop() {
    if (!this._started) return this._state(null, "neutral", 0, null);
    if (!this._playing) {
      if (this._countdown > 0) {
        this._countdown -= 1;
        return this._conceal(null);
      }
      this._playing = true;
      this._next = minKey(this._buffer);
      this._ref = this._next;
    }
    if (this.skip && this._buffer.size > 0 && this._newest - this._next >= 2 * this.depth) this._catchUp();
    const slot = this._next;
    this._next += 1;
    this._ref = this._next;
    this._prune();
    const packet = this._buffer.get(slot);
    if (packet === undefined) {
      this._counts.concealed += 1;
      return this._conceal(((slot % SEQ_MODULO) + SEQ_MODULO) % SEQ_MODULO);
    }
    this._buffer.delete(slot);
    this._rotation = packet.rotation;
    this._translation = packet.translation;
    if (packet.face) {
      this._residuals = packet.residuals;
      this._q = packet.q;
      this._serial = packet.serial;
      this._shade = packet.shade;
      this._weight = 1.0;
      this._easing = false;
      this._since = 0;
      return this._state(packet.seq, "received", packet.flags, packet.arrival_s);
    }
    this._advance(true);
    return this._state(packet.seq, "face_lost", packet.flags, packet.arrival_s);
  }

  // -- packets ---------------------------------------------------------------------------

  /** [packet, its bytes, null], or [null, null, why] when it is not a valid packet. */
  static _decode(data, arrivalS) {
    const raw = bytesOf(data);
    if (raw === null) return [null, null, "type"];
    if (raw.length !== PACKET_BYTES) return [null, null, "size"];
    let frame;
    try {
      frame = decode(raw);
    } catch (error) {
      if (error instanceof PacketError) return [null, null, error.reason];
      throw error;
    }
    const face = Boolean(frame.flags & Flag.FACE_PRESENT) && !(frame.flags & Flag.TRACKING_LOST);
    return [{
      seq: frame.seq, flags: frame.flags, rotation: rotationMatrix(frame.rotation),
      translation: Float64Array.from(frame.translation), residuals: frame.residuals, q: frame.q,
      arrival_s: arrivalS, serial: frame.serial, shade: frame.shade, face,
    }, raw, null];
  }

  _offset(value) {
    this._offsets.push(value);
    if (this._offsets.length > JITTER_PACKETS) this._offsets.shift();
  }

  /** Rule 1: a far packet is a candidate; its successor confirms a new stream. */
  _far(packet, raw) {
    const cand = this._candidate;
    if (cand !== null && packet.seq === (cand[0].seq + 1) % SEQ_MODULO) {
      this._restart([cand, [packet, raw]], true);
      return;
    }
    if (cand !== null && sameBytes(raw, cand[1])) {
      this._counts.duplicate += 1;
      return;
    }
    if (cand !== null) this._counts.stray += 1;
    this._candidate = [packet, raw];
  }

  /** A packet behind the playout point: dropped, unless it completes rule 2's run. */
  _late(packet, raw) {
    if (this._lateRun === 0) this._lateStart = packet.arrival_s;
    this._lateRun += 1;
    const span = packet.arrival_s - this._lateStart;
    if ((this._lateRun >= 2 && span > this.depth / this.rateHz + EPS) || this._lateRun >= this.window) {
      this._restart([[packet, raw]], true);
      return;
    }
    this._counts.late += 1;
  }

  /** Start a new stream from these [packet, bytes] pairs (in sequence order). */
  _restart(packets, count) {
    this._counts.discarded += this._buffer.size;
    this._counts.restarts += count ? 1 : 0;
    this._buffer.clear();
    this._seen.clear();
    this._candidate = null;
    this._lateRun = 0;
    this._started = true;
    this._playing = false;
    this._countdown = this.depth;
    this._ref = packets[0][0].seq;
    this._offsets = [];
    for (const [packet, raw] of packets) {
      const ext = this._ref + serialDistance(packet.seq, this._ref % SEQ_MODULO);
      this._buffer.set(ext, packet);
      this._seen.set(ext, raw);
      this._offset(packet.arrival_s - ext / this.rateHz);
    }
    this._newest = Math.max(...this._buffer.keys());
  }

  /** The skip rule: give up slots when the latency has grown. */
  _catchUp() {
    const target = this._newest - this.depth;
    if (!this._buffer.has(this._next)) {
      this._skip(Math.min(target, minKey(this._buffer)));
      return;
    }
    let inside = 0;
    for (const e of this._buffer.keys()) if (this._next <= e && e < target) inside += 1;
    if (inside === target - this._next) this._skip(target);
  }

  /** Move the playout point forward to ``target``, dropping the slots before it. */
  _skip(target) {
    this._counts.skipped += target - this._next;
    for (const e of [...this._buffer.keys()]) {
      if (e < target) {
        this._buffer.delete(e);
        this._counts.discarded += 1;
      }
    }
    this._next = target;
  }

  /** Forget the seen slots farther behind than the window (rule 1 covers those). */
  _prune() {
    if (this._seen.size > 4 * this.window) {
      const floor = this._next - this.window;
      for (const e of [...this._seen.keys()]) if (e < floor) this._seen.delete(e);
    }
  }

  // -- concealment -----------------------------------------------------------------------

  /** One slot without a face-present packet: hold, or ease the weight toward 0. */
  _advance(faceLost) {
    this._since += 1;
    if (!this._easing) {
      if (faceLost) {
        this._easing = true;
        this._easeBegin = this._since - 1.0;
      } else if (this._since > this.holdS * this.rateHz + EPS) {
        this._easing = true;
        this._easeBegin = this.holdS * this.rateHz;
      }
    }
    if (this._easing) {
      const span = this.easeS * this.rateHz;
      const p = span <= 0 ? 1.0 : Math.min(Math.max((this._since - this._easeBegin) / span, 0.0), 1.0);
      this._weight = Math.min(this._weight, 1.0 - p * p * (3.0 - 2.0 * p));
    }
  }

  _conceal(seq) {
    this._advance(false);
    const status = !this._easing ? "held" : this._weight > 0 ? "easing" : "neutral";
    return this._state(seq, status, 0, null);
  }

  _state(seq, status, flags, arrivalS) {
    const w = this._weight;
    let residuals, q;
    if (w >= 1.0) {
      residuals = this._residuals;
      q = this._q;
    } else if (w <= 0.0) {
      residuals = ZERO_RESIDUALS;
      q = this._restQ;
    } else {
      // float32 arithmetic, as numpy's: each operation rounded to float32
      const wf = Math.fround(w);
      residuals = this._residuals.map((r) => Math.fround(r * wf));
      q = this._q.map((v, i) => Math.fround(this._restQ[i] + Math.fround(Math.fround(v - this._restQ[i]) * wf)));
    }
    return {
      seq, rotation: this._rotation, translation: this._translation, residuals, q, flags, status,
      weight: w, arrival_s: arrivalS, serial: this._serial, shade: this._shade,
    };
  }
}

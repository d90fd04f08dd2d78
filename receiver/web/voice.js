/**
 * The page's voice: voice packets (protocol/voice.py) in, sound out through WebAudio, in
 * step with the face.
 *
 * A voice packet is ``0xA0, seq (u16), Opus bytes, CRC-16`` (protocol/voice.py): ``check``
 * refuses anything else by the same rules and reasons ("size", "kind", "reserved", "crc"), so
 * a corrupt packet is counted and never decoded into noise. Its 16-bit seq is extended to the
 * frame number nearest the newest seen (protocol/voice.py's ``unwrap``).
 *
 * Decoding: WebCodecs' ``AudioDecoder`` ("opus", 48 kHz, mono), one 20-ms frame per packet.
 * WebCodecs has no loss concealment and no FEC: a frame whose packet never came is silence
 * (counted ``concealed``), faded in and out over ``FADE_S`` at its edges so the gap clicks
 * less.
 *
 * When a frame plays: frame ``j`` was captured at ``c(j) = voiceOrigin + j * 20 ms`` on the
 * sender's clock, and the face's slot ``n`` at ``origin + n / rate`` (the Hello's
 * ``voice_origin_s``, ``clock_origin_s``, ``rate_hz``). The face plays on arrival, so its
 * delay from capture to the page is its transit ``a - c``, whose least value over the last
 * ``WINDOW`` face packets (``faceTransit``: ``PageVoice.face``) is the link's delay without
 * its jitter; the voice takes the same delay plus a margin for its own jitter, ``target``
 * frames of 20 ms, chosen as receiver/jitterbuffer.py chooses its depth (the spread of the
 * last ``WINDOW`` voice packets' transits, plus a frame, within ``MIN_DEPTH .. MAX_DEPTH``).
 * Frame ``j`` is scheduled at ``c(j) + faceTransit + target * 20 ms`` on the page's clock
 * (performance.now(), turned into the AudioContext's clock), so the sound trails the face by
 * about that margin: within what viewers accept (ITU-R BT.1359: up to 125 ms behind). A frame
 * decoded after its time is ``late`` and dropped. The schedule follows the link: when the
 * face's delay or the margin changes, the frames after it move by the change (a gap or an
 * overlap of that length, once).
 *
 * Start: browsers start sound only after the user's gesture; ``start()`` (the page calls it
 * on the first click, or at once where the page is allowed to play) creates the
 * AudioContext. Before it, packets are checked and counted but not decoded.
 *
 * ``stats`` (window.facewire.voice): received, corrupt (by reason), decoded, played,
 * concealed, late, target (frames), and ``skew_ms``: for the last ``WINDOW`` frames played,
 * the sound's latency (capture to its scheduled start) minus the face's (capture to drawn, of
 * the last face frame drawn: ``drawn``), ms; positive: the sound is behind the face.
 */

import {crc16} from "./packet.js";

export const KIND = 0xa;
export const HEADER_BYTES = 3;
export const CRC_BYTES = 2;
export const MAX_VOICE_BYTES = 65; // protocol/voice.py: 3 + 60 + 2
export const FRAME_S = 0.02;
export const SAMPLE_RATE = 48000;
export const MIN_DEPTH = 2; // receiver/jitterbuffer.py
export const MAX_DEPTH = 10;
export const WINDOW = 50;
export const FADE_S = 0.003;
const SEQ_MODULO = 1 << 16;

/** The reason ``bytes`` (a Uint8Array) is not a voice packet, or null (protocol/voice.py). */
export function check(bytes) {
  if (bytes.length < HEADER_BYTES + 1 + CRC_BYTES || bytes.length > MAX_VOICE_BYTES) return "size";
  if (bytes[0] >> 4 !== KIND) return "kind";
  if (bytes[0] & 0x0f) return "reserved";
  const end = bytes.length - CRC_BYTES;
  if (crc16(bytes.subarray(0, end)) !== ((bytes[end] << 8) | bytes[end + 1])) return "crc";
  return null;
}

/** Whether a message on the stream claims to be a voice packet (its first nibble). */
export function isVoice(bytes) {
  return bytes.length > 0 && bytes[0] >> 4 === KIND;
}

/** protocol/voice.py's ``unwrap``: the number nearest ``last`` whose value mod 2**16 is seq. */
export function unwrap(seq, last) {
  if (last === null) return seq;
  let delta = (((seq - last) % SEQ_MODULO) + SEQ_MODULO) % SEQ_MODULO;
  if (delta >= SEQ_MODULO / 2) delta -= SEQ_MODULO;
  return last + delta;
}

export class PageVoice {
  /** ``now``: the page's clock, seconds (performance.now() / 1000). */
  constructor(now) {
    this.now = now;
    this.context = null;
    this.decoder = null;
    this.hello = null;
    this.newest = null;
    this.voiceTransits = [];
    this.faceTransits = [];
    this.pending = new Map(); // frame number -> play time (page clock) of a frame being decoded
    this.nextFrame = null; // the frame the schedule expects next
    this.shift = 0; // AudioContext time minus the page's clock
    this.stats = {received: 0, corrupt: {size: 0, kind: 0, reserved: 0, crc: 0}, decoded: 0,
      played: 0, concealed: 0, late: 0, target: MIN_DEPTH, skew_ms: []};
    this.faceLatency = null; // capture to drawn of the last face frame drawn, s
  }

  /** Create the AudioContext and the decoder (after a user gesture, or where allowed). */
  start() {
    if (this.context !== null || typeof AudioDecoder === "undefined") return this.context !== null;
    this.context = new AudioContext({sampleRate: SAMPLE_RATE, latencyHint: "interactive"});
    this.shift = this.context.currentTime - this.now();
    this.openDecoder();
    return true;
  }

  openDecoder() {
    this.decoder = new AudioDecoder({
      output: (data) => this.play(data),
      error: () => { this.decoder = null; }, // a broken stream: opened again on the next packet
    });
    this.decoder.configure({codec: "opus", sampleRate: SAMPLE_RATE, numberOfChannels: 1});
  }

  /** A new Hello: the voice's origin and the face's clock (a new stream starts over). */
  adopt(hello) {
    this.hello = hello;
    this.newest = null;
    this.nextFrame = null;
    this.voiceTransits = [];
    this.faceTransits = [];
  }

  /** A face packet's slot ``n`` arrived at ``arrival`` (page clock): its transit. */
  face(n, arrival) {
    const origin = this.hello?.clock_origin_s;
    if (typeof origin !== "number") return;
    this.faceTransits.push(arrival - (origin + n / this.hello.rate_hz));
    if (this.faceTransits.length > WINDOW) this.faceTransits.shift();
  }

  /** The face's slot ``n`` was drawn at ``t`` (page clock): its latency, for ``skew_ms``. */
  drawn(n, t) {
    const origin = this.hello?.clock_origin_s;
    if (typeof origin === "number" && this.faceTransits.length > 0) {
      // the page's clock and the sender's differ by the unknown offset; the transits carry it
      this.faceLatency = t - (origin + n / this.hello.rate_hz) - Math.min(...this.faceTransits);
    }
  }

  /** One voice packet (a Uint8Array) that arrived at ``arrival``: null, or why refused. */
  push(bytes, arrival) {
    const reason = check(bytes);
    if (reason !== null) {
      this.stats.corrupt[reason] += 1;
      return reason;
    }
    this.stats.received += 1;
    const origin = this.hello?.voice_origin_s;
    if (typeof origin !== "number" || this.faceTransits.length === 0) return null;
    const j = unwrap((bytes[1] << 8) | bytes[2], this.newest);
    this.newest = this.newest === null ? j : Math.max(this.newest, j);
    const capture = origin + j * FRAME_S;
    this.voiceTransits.push(arrival - capture);
    if (this.voiceTransits.length > WINDOW) this.voiceTransits.shift();
    const spread = Math.max(...this.voiceTransits) - Math.min(...this.voiceTransits);
    this.stats.target = Math.min(MAX_DEPTH, Math.max(MIN_DEPTH, Math.ceil(spread / FRAME_S) + 1));
    if (this.context === null) return null;
    if (this.decoder === null || this.decoder.state === "closed") this.openDecoder();
    const faceDelay = Math.min(...this.faceTransits);
    const at = capture + faceDelay + this.stats.target * FRAME_S;
    if (this.nextFrame !== null && j > this.nextFrame) this.stats.concealed += j - this.nextFrame;
    if (this.nextFrame === null || j >= this.nextFrame) this.nextFrame = j + 1;
    this.pending.set(j, {at, capture, faceDelay});
    this.decoder.decode(new EncodedAudioChunk({type: "key", timestamp: Math.round(j * FRAME_S * 1e6),
      data: bytes.subarray(HEADER_BYTES, bytes.length - CRC_BYTES)}));
    return null;
  }

  /** A decoded frame: scheduled at its time, or dropped when that time has passed. */
  play(data) {
    const j = Math.round(data.timestamp / (FRAME_S * 1e6));
    const when = this.pending.get(j);
    this.pending.delete(j);
    this.stats.decoded += 1;
    const samples = new Float32Array(data.numberOfFrames);
    data.copyTo(samples, {planeIndex: 0, format: "f32-planar"});
    data.close();
    if (when === undefined || this.context === null) return;
    const start = when.at + this.shift;
    if (start < this.context.currentTime) {
      this.stats.late += 1;
      return;
    }
    const buffer = this.context.createBuffer(1, samples.length, SAMPLE_RATE);
    buffer.copyToChannel(samples, 0);
    const node = this.context.createBufferSource();
    node.buffer = buffer;
    node.connect(this.context.destination);
    node.start(start);
    this.stats.played += 1;
    if (this.faceLatency !== null) {
      const soundLatency = when.at - when.capture - when.faceDelay; // beyond the link's delay
      this.stats.skew_ms.push((soundLatency - this.faceLatency) * 1000);
      if (this.stats.skew_ms.length > WINDOW) this.stats.skew_ms.shift();
    }
  }
}

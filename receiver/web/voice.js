/**
 * The page's voice: voice packets (protocol/voice.py) in, sound out through WebAudio, in step
 * with the face.
 *
 * A voice packet is ``0xA0, seq (u16), Opus bytes, CRC-16`` (protocol/voice.py): ``check``
 * refuses anything else by the same rules and reasons ("size", "kind", "reserved", "crc"), so
 * a corrupt packet is counted and never decoded into noise.
 *
 * Decoding: WebCodecs' ``AudioDecoder`` ("opus", 48 kHz, mono), one 20-ms frame per packet.
 *
 * Loss. WebCodecs has no loss concealment and no FEC, so the page conceals as a decoder's PLC
 * would, from the last frame played. Behind every frame it schedules, it schedules a *tail*
 * of ``CONCEAL_FRAMES`` frames to start where the frame ends: its ``k``-th frame (k = 1, 2,
 * ...) is that frame ``x`` mirrored on odd ``k`` (``x`` reversed: it starts on the sample
 * ``x`` ended on) and as is on even ``k``, so that every join is continuous, times a gain
 * falling linearly over the frame from ``1 - (k - 1) / CONCEAL_FRAMES`` to ``1 - k /
 * CONCEAL_FRAMES``. The next frame scheduled stops the tail where it starts. So a frame that
 * never comes (or comes too late) is concealed by the tail, a run of them fades to silence
 * over ``CONCEAL_FRAMES`` frames rather than stopping dead, and nothing is decided before a
 * frame's time (no timer, and nothing to know at once: the audio clock stops the tail). When
 * a frame is scheduled ``gap`` frames past the last one scheduled, the first
 * ``min(gap, CONCEAL_FRAMES)`` are counted ``concealed`` and the rest ``silent``. Frame numbers
 * are the seq extended (``unwrap``); a jump of more than ``RESTART_FRAMES`` is another stream
 * (the sender started again), whose frames are numbered afresh and count nothing lost.
 *
 * When a frame plays. The gateway's ``clock`` messages give every voice frame's capture on the
 * page's clock (stats.js ``voiceCapture``) as they give every face slot's (``capture``). The
 * face plays on arrival, so its latency (capture to drawn, ``drawn``: the median of the last
 * ``WINDOW`` frames drawn) is what the sound must match. Frame ``j``, captured at ``c(j)``, is
 * scheduled at ``c(j) + L``, ``L`` the larger of the face's latency and the voice's own need:
 * the largest transit (arrival less capture) of the last ``WINDOW`` voice packets plus
 * ``DECODE_S``, so that a packet as late as any lately seen is decoded before its time. Face
 * and sound then leave with the same latency unless the voice's path is the slower (the
 * sound then trails by the difference). A frame decoded after its time is ``late`` and
 * dropped. ``L`` follows the link: up at once, down by at most ``SLEW`` per frame (so that a
 * face that speeds up does not leave the frames in flight late).
 * Before the clock is known (no ``clock`` message with the voice's origin yet), packets are
 * counted ``unclocked`` and not played.
 *
 * Start: browsers start sound only after the user's gesture; ``start()`` makes the
 * AudioContext (the page calls it at once and ``resume()`` on the first click; where the page
 * may play, as in the tests, it plays at once).
 *
 * ``stats`` (window.facewire.voice): received, corrupt (by reason), unclocked, decoded, played,
 * concealed, silent, late, ``latency_ms`` (the L of the last frame scheduled), ``state`` (the
 * AudioContext's, or "none"), ``skew_ms``: for the last ``WINDOW`` frames played, the
 * sound's latency (capture to its scheduled start) less the latency of the first face frame
 * drawn at or after that start, ms; positive: the sound is behind; and ``skews``: how many
 * skews were measured in all (the newest ``skews - before`` of ``skew_ms`` are new since a
 * reading of ``before``).
 */

import {crc16} from "./packet.js";

export const KIND = 0xa;
export const HEADER_BYTES = 3;
export const CRC_BYTES = 2;
export const MAX_VOICE_BYTES = 65; // protocol/voice.py: 3 + 60 + 2
export const FRAME_S = 0.02;
export const SAMPLE_RATE = 48000;
export const WINDOW = 50;
export const DECODE_S = 0.01;
export const SLEW = 0.001;
const SEQ_WRAP = 65536;
export const CONCEAL_FRAMES = 5;
export const RESTART_FRAMES = 250; // a jump of more than 5 s in the numbers: another stream

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

/** ``seq`` (16 bits) extended to the integer nearest ``last`` (protocol/voice.py ``unwrap``);
 * ``seq`` itself when there is no ``last``. */
export function unwrap(seq, last) {
  if (last === null) return seq;
  return last + ((((seq - last) % SEQ_WRAP) + SEQ_WRAP + SEQ_WRAP / 2) % SEQ_WRAP) - SEQ_WRAP / 2;
}

function median(values) {
  const sorted = [...values].sort((a, b) => a - b);
  return sorted.length ? sorted[sorted.length >> 1] : null;
}

export class PageVoice {
  /** ``now``: the page's clock, s; ``stats``: the page's PageStats (its clock). */
  constructor(now, stats) {
    this.now = now;
    this.clock = stats;
    this.context = null;
    this.decoder = null;
    this.transits = [];
    this.faceLatencies = [];
    this.pending = []; // {at, capture, face} of each frame being decoded, in decoding order
    this.lastFrame = null; // the newest frame number pushed (the seq extended: unwrap)
    this.latency = null; // L, s
    this.scheduled = []; // {at, capture} of frames played, until a face frame is drawn after
    this.shift = 0; // AudioContext time minus the page's clock
    this.tail = null; // the concealment behind the last frame scheduled (its node)
    this.lastPlayed = null; // the number of the last frame scheduled
    this.stats = {received: 0, corrupt: {size: 0, kind: 0, reserved: 0, crc: 0}, unclocked: 0,
      decoded: 0, played: 0, concealed: 0, silent: 0, late: 0, latency_ms: null, state: "none",
      skew_ms: [], skews: 0};
  }

  /** Make the AudioContext (or take ``context``: a test's OfflineAudioContext) and the
   * decoder; false where WebCodecs or WebAudio is missing. */
  start(context = null) {
    if (this.context !== null) return true;
    if (typeof AudioDecoder === "undefined" || typeof AudioContext === "undefined") return false;
    this.context = context ?? new AudioContext({sampleRate: SAMPLE_RATE, latencyHint: "interactive"});
    this.openDecoder();
    return true;
  }

  /** After the user's gesture: let the AudioContext play. */
  resume() {
    if (this.context !== null && this.context.state === "suspended") this.context.resume();
  }

  openDecoder() {
    this.pending = [];
    this.decoder = new AudioDecoder({
      output: (data) => this.play(data),
      error: () => { this.decoder = null; }, // opened again on the next packet
    });
    this.decoder.configure({codec: "opus", sampleRate: SAMPLE_RATE, numberOfChannels: 1});
  }

  /** A face frame (its capture on the page's clock) was drawn at ``t``. */
  drawn(capture, t) {
    if (capture === null) return;
    this.faceLatencies.push(t - capture);
    if (this.faceLatencies.length > WINDOW) this.faceLatencies.shift();
    while (this.scheduled.length && this.scheduled[0].at <= t) {
      const sound = this.scheduled.shift();
      this.stats.skew_ms.push(Math.round(((sound.at - sound.capture) - (t - capture)) * 1000));
      this.stats.skews += 1;
      if (this.stats.skew_ms.length > WINDOW) this.stats.skew_ms.shift();
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
    const seq = (bytes[1] << 8) | bytes[2];
    const capture = this.clock.voiceCapture(seq, arrival);
    if (capture === null) {
      this.stats.unclocked += 1;
      return null;
    }
    this.transits.push(arrival - capture);
    if (this.transits.length > WINDOW) this.transits.shift();
    if (this.context === null) return null;
    this.stats.state = this.context.state;
    if (this.decoder === null || this.decoder.state === "closed") this.openDecoder();
    const face = median(this.faceLatencies);
    const need = Math.max(...this.transits) + DECODE_S;
    const target = face === null ? need : Math.max(face, need);
    const latency = this.latency === null || target > this.latency ? target
      : Math.max(target, this.latency - SLEW);
    this.latency = latency;
    this.stats.latency_ms = Math.round(latency * 1000);
    const frame = unwrap(seq, this.lastFrame);
    const restart = this.lastFrame !== null && Math.abs(frame - this.lastFrame) > RESTART_FRAMES;
    this.lastFrame = this.lastFrame === null || restart ? frame : Math.max(this.lastFrame, frame);
    this.pending.push({at: capture + latency, capture, frame});
    this.decoder.decode(new EncodedAudioChunk({type: "key", timestamp: Math.round(capture * 1e6),
      data: bytes.subarray(HEADER_BYTES, bytes.length - CRC_BYTES)}));
    return null;
  }

  /** A decoded frame: scheduled at its time, or dropped when that time has passed. The
   * decoder gives one frame per packet, in order (its output timestamps are its own count
   * after a gap, so frames are matched by order, not by timestamp). */
  play(data) {
    const when = this.pending.shift();
    this.stats.decoded += 1;
    const samples = new Float32Array(data.numberOfFrames);
    data.copyTo(samples, {planeIndex: 0, format: "f32-planar"});
    data.close();
    if (when === undefined || this.context === null) return;
    this.shift = this.context.currentTime - this.now();
    const start = when.at + this.shift;
    if (this.lastPlayed !== null && Math.abs(when.frame - this.lastPlayed) > RESTART_FRAMES) {
      this.lastPlayed = null; // another stream (a sender started again): nothing lost between
    }
    if (start < this.context.currentTime || (this.lastPlayed !== null && when.frame <= this.lastPlayed)) {
      this.stats.late += 1; // its time has passed, or a later frame's has come (the tail plays)
      return;
    }
    if (this.lastPlayed !== null) {
      const gap = when.frame - this.lastPlayed - 1;
      this.stats.concealed += Math.min(gap, CONCEAL_FRAMES);
      this.stats.silent += Math.max(0, gap - CONCEAL_FRAMES);
    }
    if (this.tail !== null) this.tail.stop(start);
    this.schedule(samples, start);
    this.tail = this.schedule(tail(samples), start + samples.length / SAMPLE_RATE);
    this.lastPlayed = when.frame;
    this.stats.played += 1;
    this.scheduled.push(when);
    if (this.scheduled.length > WINDOW) this.scheduled.shift(); // no face drawn: no skew
  }

  /** Play ``samples`` at ``start`` (AudioContext time); the node. */
  schedule(samples, start) {
    const buffer = this.context.createBuffer(1, samples.length, SAMPLE_RATE);
    buffer.copyToChannel(samples, 0);
    const node = this.context.createBufferSource();
    node.buffer = buffer;
    node.connect(this.context.destination);
    node.start(start);
    return node;
  }
}

/** The concealment that follows the frame ``x`` (Float32Array): ``CONCEAL_FRAMES`` frames,
 * mirrored and faded (the module docstring, "Loss"). */
export function tail(x) {
  const n = x.length;
  const out = new Float32Array(n * CONCEAL_FRAMES);
  for (let k = 1; k <= CONCEAL_FRAMES; k++) {
    const from = 1 - (k - 1) / CONCEAL_FRAMES;
    const to = 1 - k / CONCEAL_FRAMES;
    for (let i = 0; i < n; i++) {
      const sample = k % 2 ? x[n - 1 - i] : x[i];
      out[(k - 1) * n + i] = sample * (from + (to - from) * (i / n));
    }
  }
  return out;
}

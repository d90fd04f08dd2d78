/**
 * The page's live statistics: they mirror the live statistics of receiver/stats.py
 * (``ReceiveStats.live``), measured over the last WINDOW_S seconds of performance.now() time:
 *
 *   fps        = frames rendered in the window / WINDOW_S
 *   kbit/s     = 8 * packet bytes received in the window / 1000 / WINDOW_S
 *   latency    = the median, over the window's frames that played a packet, of the time from
 *                that packet's arrival (its WebSocket message) to its frame rendered, ms
 *   glass      = glass-to-glass: the median, over the same frames, of the time from the
 *                packet's capture at the sender to its frame rendered, ms (null until a
 *                ``clock`` message came; below)
 *   loss %     = 100 * lost / slots, over the slots played in the window, ``lost`` as the
 *                Python receiver counts it: slots concealed (their packet missing) that a
 *                played packet follows, so that a sender gone (the head easing to rest, then
 *                still) loses nothing; a gap longer than MAX_GAP_S ends the stream uncounted
 *   render ms  = the page's own frame time: the median, over the last TIMED_FRAMES timed
 *                frames (main.js times one in a few), of ``FaceRenderer.render`` (the morph
 *                and the draw) until the frame is drawn (a pixel read back), so the GPU's (or
 *                the software renderer's) time is in it
 *
 * and totals since the page opened: frames, slots, lost, packets, bytes.
 *
 * The clock (protocol/clock.py). The gateway sends ``clock`` messages: ``origin_s`` and
 * ``rate_hz`` (slot n captured at origin_s + n / rate_hz) and ``now_s``, on the gateway's
 * clock. A message that arrives at ``a`` on the page's clock was sent at now_s = a + theta -
 * d, theta the gateway's clock minus the page's and d >= 0 its delay, so theta >= now_s - a:
 * the page takes the largest now_s - a of the last CLOCK_SAMPLES messages (the least
 * delayed), which errs by that message's delay (under a millisecond on one host). A played
 * packet's seq n (16 bits) is extended to the wrap nearest its arrival. A message may also
 * carry ``voice_origin_s`` (voice frame j captured at voice_origin_s + j * 20 ms, gateway's
 * clock): ``voiceCapture`` gives a voice packet's capture on the page's clock (voice.js).
 */

export const WINDOW_S = 1.0;
export const MAX_GAP_S = 10.0; // receiver/receiver.py
export const TIMED_FRAMES = 16;
export const CLOCK_SAMPLES = 16;
const SEQ_WRAP = 65536;
const VOICE_RATE_HZ = 50; // protocol/voice.py: a frame per 20 ms

function median(values) {
  if (values.length === 0) return null;
  const sorted = [...values].sort((a, b) => a - b);
  const mid = sorted.length >> 1;
  return sorted.length % 2 ? sorted[mid] : (sorted[mid - 1] + sorted[mid]) / 2;
}

const round = (x, digits) => Math.round(x * 10 ** digits) / 10 ** digits;

/** Counts and recent measurements; every time is seconds of performance.now() / 1000. */
export class PageStats {
  constructor() {
    this.totals = {frames: 0, slots: 0, lost: 0, packets: 0, bytes: 0};
    this._packets = []; // [arrival, bytes]
    this._slots = []; // [time, lost]
    this._pending = []; // the times of concealed slots no played packet followed yet
    this._frames = []; // [time, latency s | null]
    this._timed = []; // the last TIMED_FRAMES frame times, s
    this._clock = null; // the last clock message: {origin_s, rate_hz}
    this._thetas = []; // now_s - arrival of the last CLOCK_SAMPLES clock messages
  }

  /** A ``clock`` message arrived at ``arrivalS``; a malformed one is ignored (false). */
  clock(message, arrivalS) {
    const {origin_s: origin, rate_hz: rate, now_s: sent} = message;
    if (![origin, rate, sent].every(Number.isFinite) || !(rate > 0)) return false;
    const voice = Number.isFinite(message.voice_origin_s) ? message.voice_origin_s : null;
    this._clock = {origin, rate, voice};
    this._thetas.push(sent - arrivalS);
    if (this._thetas.length > CLOCK_SAMPLES) this._thetas.shift();
    return true;
  }

  /** The capture time of a played state on the page's clock, s, or null without a clock. */
  capture(state) {
    if (this._clock === null || state.arrival_s === null || state.seq === null) return null;
    return this._capture(state.seq, state.arrival_s, this._clock.origin, this._clock.rate);
  }

  /** The capture time of voice frame ``seq`` (16 bits) that arrived at ``arrivalS``, on the
   * page's clock, s; null without a clock that carries the voice's origin. */
  voiceCapture(seq, arrivalS) {
    if (this._clock === null || this._clock.voice === null) return null;
    return this._capture(seq, arrivalS, this._clock.voice, VOICE_RATE_HZ);
  }

  _capture(seq, arrivalS, origin, rate) {
    const theta = Math.max(...this._thetas);
    const m = Math.round(((arrivalS + theta - origin) * rate - seq) / SEQ_WRAP);
    return origin + (seq + SEQ_WRAP * m) / rate - theta;
  }

  /** A packet of ``size`` bytes arrived at ``arrivalS``. */
  packet(size, arrivalS) {
    this.totals.packets += 1;
    this.totals.bytes += size;
    this._packets.push([arrivalS, size]);
  }

  /** A slot was played at ``nowS`` (a FrameState with a seq) at ``rateHz``: concealed when it
   * has no arrival, counted once a played packet follows. */
  slot(nowS, state, rateHz) {
    if (state.arrival_s === null) {
      this._pending.push(nowS);
      if (this._pending.length > MAX_GAP_S * rateHz) this._pending = [];
      return;
    }
    for (const t of this._pending) this._slots.push([t, true]);
    this.totals.slots += this._pending.length + 1;
    this.totals.lost += this._pending.length;
    this._pending = [];
    this._slots.push([nowS, false]);
  }

  /** A frame was rendered at ``nowS`` from ``state``, drawn in ``renderS`` seconds when it was
   * timed (else null). */
  frame(nowS, state, renderS) {
    this.totals.frames += 1;
    const capture = this.capture(state);
    this._frames.push([nowS, state.arrival_s === null ? null : nowS - state.arrival_s,
      capture === null ? null : nowS - capture]);
    if (renderS !== null) {
      this._timed.push(renderS);
      if (this._timed.length > TIMED_FRAMES) this._timed.shift();
    }
  }

  /** The live statistics as of ``nowS``: fps, kbps, loss_percent, latency_ms, glass_ms, render_ms (null
   * when the window holds nothing to measure) and the totals. */
  live(nowS) {
    const floor = nowS - WINDOW_S;
    for (const list of [this._packets, this._slots, this._frames]) {
      let drop = 0;
      while (drop < list.length && list[drop][0] < floor) drop += 1;
      list.splice(0, drop);
    }
    const latencies = this._frames.filter(([, latency]) => latency !== null).map(([, latency]) => latency);
    const lost = this._slots.filter(([, l]) => l).length;
    const latency = median(latencies);
    const glass = median(this._frames.filter(([, , g]) => g !== null).map(([, , g]) => g));
    const render = median(this._timed);
    return {
      fps: round(this._frames.length / WINDOW_S, 1),
      kbps: round(this._packets.reduce((sum, [, n]) => sum + n, 0) * 8 / 1000 / WINDOW_S, 2),
      loss_percent: this._slots.length ? round(100 * lost / this._slots.length, 1) : null,
      latency_ms: latency === null ? null : round(1000 * latency, 1),
      glass_ms: glass === null ? null : round(1000 * glass, 1),
      render_ms: render === null ? null : round(1000 * render, 2),
      ...this.totals,
    };
  }
}

/**
 * The browser receiver's page: what receiver/receiver.py does for one live session, in the
 * browser, fed by ``facewire web`` (receiver/gateway.py; the contract is docs/DESIGN.md,
 * "Browser receiver").
 *
 * The socket: ``ws(s)://<this host>/stream<this page's query>`` (a token travels as the query,
 * on every URL the page asks). A binary message is one packet, pushed into the playout with
 * its arrival time (performance.now() / 1000); a text message is one JSON object:
 * ``status`` (the gateway has a sender or waits for one), ``hello`` (the sender's Hello: a new
 * one starts a new playout at its ``rate_hz``, as the Python receiver does), ``model`` (a base
 * model to load, model.js) and ``update`` (model version ``serial`` to load on top of version
 * serial - 1). A socket that closes is opened again after 0.5 s, doubling to 30 s while it
 * fails.
 *
 * The playout clock: a requestAnimationFrame loop pops the playout as the live Python
 * receiver does, "playing on arrival" (receiver/playout.py): at each animation frame it pops
 * while the next slot's packet is in (``ready``) or its deadline has passed (``due()``), so
 * the slots come at the stream's rate as the packets do, the display's refresh only
 * quantising them, and a lost packet is concealed when due. The last slot popped is rendered
 * (several pile up only after the tab was hidden, and the playout's skip rule then catches
 * up). Each slot is rendered with the newest model version held that is no newer than its
 * packet's ``serial`` (Q clamped to the layers held until its update arrives, counted
 * ``clamped``); a lost face eases to that version's rest Q.
 *
 * Bad input: a packet that does not decode is counted by its reason (``window.facewire.counts
 * .corrupt``); a text message that is not a known JSON object is counted ``junk``; a Hello
 * whose protocol or packet table differs from packet.js's is refused with a message (no
 * playout); a model or update that fails to load (ModelError) is refused with a visible
 * message and the last good version stays on screen.
 *
 * The rendering half (model.js, render.js, views.js) is imported apart when the page starts:
 * a browser that cannot load it still connects, plays and counts, and says why it shows no
 * face.
 *
 * The voice (voice.js): a binary message whose first nibble is the voice's kind goes to the
 * page's voice, which plays it through WebAudio in step with the face (after the user's first
 * click, as browsers require, or at once where the page may play). WebCodecs exists only in a
 * secure context (https, or localhost): elsewhere the first voice packet puts on the status
 * line, once, that the voice needs https or localhost, and the face plays on without it.
 *
 * ``window.facewire`` (for tests): ``state`` (the last FrameState played), ``stats`` (stats.js
 * live statistics, refreshed with the panel), ``voice`` (voice.js's counts and skews), ``playout`` (its counts), ``counts`` (messages,
 * packets, bytes, decoded, ignored: packets before a Hello, corrupt by reason, junk, clamped,
 * statuses: the slots played by playout status),
 * ``status`` (the status line's text), ``model`` ({sha256, held: versions held, shown}),
 * ``hello``, ``connected``; ``paused`` (settable): while true the clock neither pops nor draws
 * and the panel is not refreshed (packets are still taken in), so that the canvas, the panel and
 * ``state`` show one slot together (a test's screenshot); set false, the playout's skip rule
 * catches up.
 */

import {N_REGIONS, VERSION, sameQuantisers} from "./packet.js";
import {MAX_RATE_HZ, MIN_RATE_HZ, Playout, STATUSES} from "./playout.js";
import {PageStats} from "./stats.js";
import {PageVoice, isVoice} from "./voice.js";

const RECONNECT_MIN_S = 0.5;
const RECONNECT_MAX_S = 30.0;
const UPDATE_RETRY_MIN_S = 1.0; // a refused update is asked again, backing off as receiver/updates.py
const UPDATE_RETRY_MAX_S = 30.0;
const PANEL_EVERY_MS = 250;
// the status line's part when the stream has a voice this page cannot play (voice.js start())
const VOICE_MISSING = "no sound: the voice needs https or localhost (this browser gives WebCodecs and WebAudio only there)";
const TIMED_EVERY = 8; // one drawn frame in 8 is timed until drawn (stats.js's frame time)
const QUIET_S = 1.0; // no packet for longer: said on the status line (receiver/stats.py)
const MAX_TEXT_CHARS = 1000; // protocol/control.py: what a peer's text is cut to
const HEX64 = /^[0-9a-f]{64}$/;

const query = location.search;
const $ = (id) => document.getElementById(id);
const now = () => performance.now() / 1000;
const megabytes = (n) => `${(n / 1e6).toFixed(1)} MB`;
// a peer's text, or an error naming a URL, shown cut and without this page's query (a token)
const cut = (text) => (query ? String(text).split(query).join("") : String(text)).slice(0, MAX_TEXT_CHARS);

/** What is wrong with a Hello, or null (protocol/control.py's checks that the page relies on). */
function helloProblem(hello) {
  if (hello.protocol !== VERSION) return `hello.protocol: the sender speaks protocol version ${hello.protocol}, this page ${VERSION}`;
  if (!HEX64.test(String(hello.model_sha256))) return "hello.model_sha256: expected 64 lowercase hex digits";
  if (typeof hello.rate_hz !== "number" || !(hello.rate_hz >= MIN_RATE_HZ && hello.rate_hz <= MAX_RATE_HZ)) {
    return `hello.rate_hz: must be in [${MIN_RATE_HZ}, ${MAX_RATE_HZ}]`;
  }
  if (!Array.isArray(hello.regions) || hello.regions.length > N_REGIONS) return `hello.regions: expected at most ${N_REGIONS} names`;
  if (hello.camera === null || typeof hello.camera !== "object") return "hello.camera: missing";
  if (!sameQuantisers(hello.quantisers)) return `hello.quantisers: do not match this page's protocol version ${VERSION} table`;
  return null;
}

/** The base model's sha256 an "update" message's URL names (``/model/<sha256>/<serial>.upd``). */
function updateBase(message) {
  return /\/model\/([0-9a-f]{64})\/\d+\.upd/.exec(message.url)?.[1] ?? null;
}

/** The rendering half (model.js, render.js, views.js), loaded apart so that the page still
 * connects, plays and says what is wrong when it cannot load (a browser without what they
 * need). */
async function loadEngine() {
  const [model, render, views] = await Promise.all([import("./model.js"), import("./render.js"), import("./views.js")]);
  return {ModelError: model.ModelError, loadModel: model.loadModel, loadUpdate: model.loadUpdate,
    FaceRenderer: render.FaceRenderer, OrbitView: views.OrbitView};
}

/** A model version's rest Q per packet slot (``receiver.scene.rest_q``): each region's rest
 * state (the model's ``restQ``, or its regions' ``rest``), 0 beyond its regions. */
function restQ(model) {
  const rest = new Float32Array(N_REGIONS);
  const given = model.restQ ?? model.regions?.map((region) => region.rest) ?? [];
  rest.set(Array.from(given).slice(0, N_REGIONS));
  return rest;
}

class Page {
  constructor() {
    this.canvas = $("face");
    this.engine = null; // loadEngine()'s modules
    this.orbit = null;
    this.socket = null;
    this.attempts = 0;
    this.hello = null;
    this.helloText = "";
    this.playout = null;
    this.renderer = null;
    this.versions = []; // versions[k]: the Model of version k of the current base model
    this.updates = new Map(); // serial -> the "update" message not applied yet
    this.updateDelay = UPDATE_RETRY_MIN_S;
    this.updateTimer = null;
    this.shown = null; // the version index rendered last
    this.paused = false; // window.facewire.paused
    this.work = loadEngine().then((engine) => { // then model and update loads, one by one
      this.engine = engine;
      this.orbit = new engine.OrbitView(this.canvas);
      this.setupRenderer();
    }, (error) => {
      this.text.engine = `cannot load the renderer: ${cut(error.message ?? error)}`;
    });
    this.state = null;
    this.lastView = null;
    this.pixel = new Uint8Array(4);
    this.drawn = 0;
    this.lastPacket = null;
    this.stats = new PageStats();
    this.voice = new PageVoice(now, this.stats); // voice.js: after a click, or where allowed
    this.voiceOn = this.voice.start(); // false: no WebCodecs or WebAudio (not a secure context)
    document.addEventListener("click", () => this.voice.resume());
    this.counts = {messages: 0, packets: 0, bytes: 0, decoded: 0, ignored: 0, junk: 0, clamped: 0,
      corrupt: {size: 0, version: 0, crc: 0, reserved: 0, type: 0},
      statuses: Object.fromEntries(STATUSES.map((status) => [status, 0]))};
    this.text = {link: "connecting", sender: "", model: "", problem: "", engine: "", voice: ""};
    this.live = this.stats.live(now());
    const page = this;
    window.facewire = {
      get state() { return page.state; },
      get stats() { return page.live; },
      get voice() { return structuredClone(page.voice.stats); },
      get playout() { return page.playout === null ? null : page.playout.stats; },
      get counts() { return structuredClone(page.counts); },
      get status() { return $("status").textContent; },
      get model() {
        return {sha256: page.versions[0]?.sha256 ?? null, held: page.versions.length, shown: page.shown};
      },
      get hello() { return page.hello; },
      get connected() { return page.socket !== null && page.socket.readyState === WebSocket.OPEN; },
      get paused() { return page.paused; },
      set paused(on) {
        page.paused = false;
        page.panel(); // the panel of the slot on the canvas
        page.paused = Boolean(on);
      },
    };
    this.frame = this.frame.bind(this);
    requestAnimationFrame(this.frame);
    setInterval(() => this.panel(), PANEL_EVERY_MS);
    this.connect();
    this.panel();
  }

  // -- the socket --------------------------------------------------------------------------

  connect() {
    const scheme = location.protocol === "https:" ? "wss:" : "ws:";
    const socket = new WebSocket(`${scheme}//${location.host}/stream${query}`);
    socket.binaryType = "arraybuffer";
    this.socket = socket;
    this.text.link = "connecting to the gateway";
    socket.onopen = () => {
      this.attempts = 0;
      this.text.link = "";
    };
    socket.onmessage = (event) => this.message(event.data);
    socket.onclose = (event) => {
      const delay = Math.min(RECONNECT_MAX_S, RECONNECT_MIN_S * 2 ** this.attempts);
      this.attempts += 1;
      const why = event.reason ? `: ${cut(event.reason)}` : "";
      this.text.link = `connection to the gateway lost (code ${event.code}${why}): reconnecting in ${delay} s`;
      this.text.sender = ""; // the gateway says again on connecting
      this.panel();
      setTimeout(() => this.connect(), delay * 1000);
    };
  }

  message(data) {
    this.counts.messages += 1;
    if (typeof data !== "string") {
      this.packet(data);
      return;
    }
    let message;
    try {
      message = JSON.parse(data);
    } catch {
      this.counts.junk += 1;
      return;
    }
    const type = message !== null && typeof message === "object" ? message.type : undefined;
    if (type === "status") this.status(message);
    else if (type === "hello") this.adopt(message);
    else if (type === "model") {
      // the updates that follow are of the session this message starts (the gateway sends
      // the model again, from version 0, when a sender restarts a session of the same model)
      this.updates = new Map();
      this.enqueue(() => this.loadBase(message));
    }
    else if (type === "update") this.update(message);
    else if (type === "clock") {
      if (!this.stats.clock(message, now())) this.counts.junk += 1;
    }
    else this.counts.junk += 1;
  }

  packet(data) {
    const arrival = now();
    const bytes = new Uint8Array(data);
    if (isVoice(bytes)) { // the voice: voice.js, beside the face's playout
      this.voice.push(bytes, arrival);
      if (!this.voiceOn && this.text.voice === "") {
        this.text.voice = VOICE_MISSING;
        this.panel();
      }
      return;
    }
    this.counts.packets += 1;
    this.counts.bytes += data.byteLength;
    this.stats.packet(data.byteLength, arrival);
    this.lastPacket = arrival;
    if (this.playout === null) {
      this.counts.ignored += 1;
      return;
    }
    const reason = this.playout.push(data, arrival);
    if (reason === null) this.counts.decoded += 1;
    else this.counts.corrupt[reason] += 1;
  }

  status(message) {
    const text = typeof message.text === "string" ? cut(message.text) : "";
    if (message.sender === "waiting") {
      this.text.sender = text && text !== "waiting for the sender" ? `waiting for the sender (${text})` : "waiting for the sender";
    } else {
      this.text.sender = text || "sender connected";
    }
    this.panel();
  }

  /** A Hello: a new one (another sender, or the same restarted) starts a new playout. */
  adopt(hello) {
    const {type, ...fields} = hello;
    const text = JSON.stringify(fields);
    if (text === this.helloText && this.playout !== null) return; // the same session, rejoined
    const problem = helloProblem(fields);
    if (problem !== null) {
      this.text.problem = `sender refused: ${cut(problem)}`;
      this.playout = null;
      this.panel();
      return;
    }
    const renewed = this.hello !== null;
    this.text.problem = "";
    this.hello = fields;
    this.helloText = text;
    const shown = this.versions[this.shown ?? 0];
    this.playout = new Playout(fields.rate_hz, {restQ: shown === undefined ? null : restQ(shown)});
    if (renewed) this.dropRenderer(); // its camera is the old Hello's
    this.setupRenderer();
  }

  // -- the model and its versions ------------------------------------------------------------

  enqueue(task) {
    this.work = this.work.then(task).catch((error) => {
      this.text.problem = `page error: ${cut(error.message ?? error)}`;
    }).finally(() => this.panel());
  }

  async loadBase(message) {
    if (this.engine === null) return; // said on the status line already
    if (this.versions.length && this.versions[0].sha256 === message.sha256) {
      // a new session of the model held: back to its file (version 0), then its own updates
      this.versions = [this.versions[0]];
      this.shown = null;
      this.text.model = `model ${megabytes(Number(message.bytes) || 0)}, version 0`;
      await this.applyUpdates();
      return;
    }
    this.text.model = `loading model ${megabytes(Number(message.bytes) || 0)}`;
    this.panel();
    let model;
    try {
      model = await this.engine.loadModel(message, query);
    } catch (error) {
      this.refused("model refused", error);
      return;
    }
    this.versions = [model];
    this.updates = new Map([...this.updates].filter(([, m]) => updateBase(m) === model.sha256));
    this.shown = null;
    this.text.model = `model ${megabytes(Number(message.bytes) || 0)}, version 0`;
    this.dropRenderer(); // another base model: a new renderer
    this.setupRenderer();
    await this.applyUpdates();
  }

  update(message) {
    if (!Number.isInteger(message.serial) || message.serial < 1 || typeof message.url !== "string") {
      this.counts.junk += 1;
      return;
    }
    this.updates.set(message.serial, message);
    this.enqueue(() => this.applyUpdates());
  }

  /** Load the updates held of the current base model, in serial order, from the version after
   * the newest held. */
  async applyUpdates() {
    while (this.versions.length && this.updates.has(this.versions.length)) {
      const serial = this.versions.length;
      const message = this.updates.get(serial);
      if (updateBase(message) !== this.versions[0].sha256) return; // of a model still loading
      let model;
      try {
        model = await this.engine.loadUpdate(this.versions[serial - 1], message, query);
      } catch (error) {
        this.refused(`model update ${serial} refused`, error);
        clearTimeout(this.updateTimer);
        this.updateTimer = setTimeout(() => this.enqueue(() => this.applyUpdates()), this.updateDelay * 1000);
        this.updateDelay = Math.min(UPDATE_RETRY_MAX_S, 2 * this.updateDelay);
        return;
      }
      this.versions.push(model);
      this.updates.delete(serial);
      this.updateDelay = UPDATE_RETRY_MIN_S;
      this.text.model = `model version ${serial}`;
    }
  }

  /** Whether the model held is the one the Hello names (another sender's is not drawn). */
  get matching() {
    return this.hello !== null && this.versions.length > 0 && this.versions[0].sha256 === this.hello.model_sha256;
  }

  refused(what, error) {
    const why = error instanceof this.engine.ModelError ? error.message : `could not load (${error.message ?? error})`;
    const keep = this.matching ? `showing the last good one (version ${this.versions.length - 1})` : "no model to show";
    this.text.model = `${what}: ${cut(why)}; ${keep}`;
  }

  /** Free the renderer's GPU objects: the next one takes the canvas's context. */
  dropRenderer() {
    if (this.renderer === null) return;
    this.renderer.release();
    this.renderer = null;
  }

  setupRenderer() {
    if (this.renderer !== null || this.engine === null || !this.matching) return;
    try {
      this.renderer = new this.engine.FaceRenderer(this.canvas, this.versions[0], this.hello);
      this.shown = 0;
    } catch (error) {
      this.text.problem = `cannot render: ${cut(error.message ?? error)}`;
    }
  }

  /** The version to render a slot with: the newest held that is no newer than its packet's. */
  follow(serial) {
    const k = Math.min(serial, this.versions.length - 1);
    if (serial > k) this.counts.clamped += 1;
    if (k !== this.shown) {
      this.renderer.setModel(this.versions[k]);
      this.playout.restQ = restQ(this.versions[k]);
      this.shown = k;
    }
  }

  // -- the clock -------------------------------------------------------------------------

  frame() {
    requestAnimationFrame(this.frame);
    const playout = this.playout;
    if (playout === null || this.paused) return;
    let state = null;
    for (let pops = 0; pops <= playout.window; pops++) {
      const due = playout.due();
      if (!(playout.ready || (due !== null && now() >= due))) break;
      const popped = playout.pop();
      if (popped.seq === null) continue; // a countdown pop plays no slot
      this.stats.slot(now(), popped, playout.rateHz);
      this.counts.statuses[popped.status] += 1;
      state = popped;
    }
    if (state !== null) this.state = state;
    if (this.renderer === null || this.state === null) return;
    const view = this.orbit.view;
    const viewText = JSON.stringify(view);
    if (state === null && viewText === this.lastView) return; // nothing new to draw
    this.lastView = viewText;
    this.follow(this.state.serial);
    const start = performance.now();
    this.renderer.render(this.state, view);
    this.drawn += 1;
    const timed = this.drawn % TIMED_EVERY === 0;
    if (timed) {
      // one pixel read back waits until the frame is drawn: the whole frame's cost (the GPU's,
      // or the software renderer's in another process), not only the calls' submission; only
      // one frame in TIMED_EVERY, since the wait blocks the page's thread (its packets'
      // arrival times with it)
      const gl = this.canvas.getContext("webgl2"); // the renderer's: a canvas keeps its context
      gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, this.pixel);
    }
    const end = performance.now();
    if (state !== null) {
      this.stats.frame(end / 1000, state, timed ? (end - start) / 1000 : null);
      this.voice.drawn(this.stats.capture(state), end / 1000);
    }
  }

  // -- what the viewer reads ---------------------------------------------------------------

  panel() {
    if (this.paused) return;
    const t = now();
    this.live = this.stats.live(t);
    const quiet = this.playout !== null && this.lastPacket !== null && t - this.lastPacket > QUIET_S
      ? `no packets for ${(t - this.lastPacket).toFixed(0)} s` : "";
    const parts = [this.text.link, this.text.sender, quiet, this.text.problem, this.text.engine, this.text.model,
      this.text.voice];
    $("status").textContent = parts.filter(Boolean).join(" · ");
    const s = this.live;
    const show = (id, value) => { $(id).textContent = value; };
    show("fps", s.fps.toFixed(1));
    show("kbps", s.kbps.toFixed(2));
    show("loss", s.loss_percent === null ? "-" : `${s.loss_percent.toFixed(1)} % (${s.lost} lost in all)`);
    show("latency", s.latency_ms === null ? "-" : `${s.latency_ms.toFixed(0)} ms`);
    show("glass", s.glass_ms === null ? "-" : `${s.glass_ms.toFixed(0)} ms`);
    show("render", s.render_ms === null ? "-" : `${s.render_ms.toFixed(1)} ms`);
    show("state", this.state === null ? "-" : `${this.state.status}, seq ${this.state.seq}`);
    show("version", this.shown === null ? "-" : `${this.shown} (${this.versions.length} held)`);
  }
}

new Page();

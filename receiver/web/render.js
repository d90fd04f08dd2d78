// The page's renderer: a FrameState to pixels with WebGL2. Mirrors receiver/scene.py
// (StateRenderer.render: vertices = rig.morph(rig.from_tangent(residuals)), the sender's camera
// or a virtual one, the state's Q and light) and receiver/render.py (FaceRenderer: the
// neutral texture, each region area composited over it from its premultiplied volume, the
// light's gain at the end), with models/infra/raster.py's camera and receiver/views.py's
// views.
//
// Camera (models/infra/raster.py): X_cam = R X + t, x right, y up, looking along -z; pixel
// centres at integers, so with w_clip = -Z
//     P = [2fx/W 0 1-2(cx+1/2)/W 0; 0 2fy/H 2(cy+1/2)/H-1 0; 0 0 -(f+n)/(f-n) -2fn/(f-n); 0 0 -1 0]
// (near n = 10 mm, far f = 10000 mm). The sender's view (receiver/views.py sender_view) is
// the Hello's intrinsics resized to the canvas, fx' = s fx, cx' = s (cx + 1/2) - 1/2, with
// the state's pose. The orbit view (views.js) is a square-pixel camera (the framing's field
// of view, models/framing.py) on models/infra/raster.py's orbit_pose around the head centre
// c, the head turning by the state's rotation about c, as receiver/views.py's virtual_view.
//
// Regions (receiver/render.py): each area is a 2D array texture of its k layers, RGBA16F,
// mipmapped per layer (MIP_LEVELS), and the shader samples layers i = floor(Q) and i + 1 and
// mixes them with weight Q - i: at full resolution exactly a 3D texture's trilinear sampling
// (TEXTURE_3D, LINEAR, at depth (Q + 0.5) / k), but a 3D texture's mipmaps would halve its
// depth and mix appearance states, and the regions must be mipmapped or they alias against
// the mipmapped skin around them. Like Python, the triangles are drawn in groups by the areas
// their UV box meets (models/draworder.py), each group by a program compositing only those.
// No multisampling, as Python's default.
//
// Culling: back faces are not drawn. The mesh's triangles wind counter-clockwise seen from
// outside, so a triangle facing away from the camera is one the depth test would hide behind
// the front of the head; SwiftShader (a CPU rasteriser) still shades it when it is drawn
// before what hides it, and the plain group (the back of the head among it) comes first.
// Culled, the frame costs a third to a half as much; the picture differs from Python's
// (which draws them) only where a back face showed through a crack: tens of pixels at the
// mouth's corners with the mouth open.

import { MIP_LEVELS, regionAreas, triangleGroups } from "./model.js";

const NEAR = 10, FAR = 10000;

// One GLSL source with the Python renderer (receiver/render.py): face.vert and face.frag,
// fetched beside this module with its query (a token: index.html's import map gives every
// module the page's query). A face.frag line ending in EACH_AREA is written once per area
// the program composites, "#" replaced by the area's index (render.py's fragment_source).
const EACH_AREA = "// each area";
const [VERTEX, FRAGMENT] = await Promise.all(["face.vert", "face.frag"].map(async (name) => {
  const url = new URL(name, import.meta.url);
  url.search = new URL(import.meta.url).search;
  const response = await fetch(url);
  if (!response.ok) throw new Error(`${name}: HTTP ${response.status}`);
  return response.text();
}));

function fragment(areas) {
  return FRAGMENT.split("\n").flatMap((line) => line.endsWith(EACH_AREA)
    ? areas.map((a) => line.replaceAll("#", String(a))) : [line]).join("\n");
}

// 4x4 row-major products and the column-major Float32Array GLSL wants.
function multiply(a, b) {
  const out = new Float64Array(16);
  for (let i = 0; i < 4; i++)
    for (let j = 0; j < 4; j++) {
      let s = 0;
      for (let k = 0; k < 4; k++) s += a[4 * i + k] * b[4 * k + j];
      out[4 * i + j] = s;
    }
  return out;
}

function columnMajor(m) {
  const out = new Float32Array(16);
  for (let i = 0; i < 4; i++) for (let j = 0; j < 4; j++) out[4 * j + i] = m[4 * i + j];
  return out;
}

// models/infra/raster.py Camera.projection_matrix, row-major.
export function projection(fx, fy, cx, cy, width, height) {
  return new Float64Array([
    2 * fx / width, 0, 1 - 2 * (cx + 0.5) / width, 0,
    0, 2 * fy / height, 2 * (cy + 0.5) / height - 1, 0,
    0, 0, -(FAR + NEAR) / (FAR - NEAR), -2 * FAR * NEAR / (FAR - NEAR),
    0, 0, -1, 0]);
}

// [R t; 0 1] of a (3, 3) row-major rotation and a translation.
function poseMatrix(r, t) {
  return new Float64Array([r[0], r[1], r[2], t[0], r[3], r[4], r[5], t[1],
                           r[6], r[7], r[8], t[2], 0, 0, 0, 1]);
}

// models/infra/raster.py orbit_pose (yaw, pitch in radians): R (row-major) and t.
export function orbitPose(yaw, pitch, distance, target) {
  const cy = Math.cos(yaw), sy = Math.sin(yaw), cp = Math.cos(pitch), sp = Math.sin(pitch);
  const m = new Array(9);  // camera_to_model = turn @ tilt
  const turn = [cy, 0, sy, 0, 1, 0, -sy, 0, cy];
  const tilt = [1, 0, 0, 0, cp, sp, 0, -sp, cp];
  for (let i = 0; i < 3; i++)
    for (let j = 0; j < 3; j++) {
      let s = 0;
      for (let k = 0; k < 3; k++) s += turn[3 * i + k] * tilt[3 * k + j];
      m[3 * i + j] = s;
    }
  const centre = [0, 1, 2].map((i) => target[i] + distance * m[3 * i + 2]);
  const rotation = [m[0], m[3], m[6], m[1], m[4], m[7], m[2], m[5], m[8]];  // transpose
  const translation = [0, 1, 2].map((i) => -(rotation[3 * i] * centre[0] +
    rotation[3 * i + 1] * centre[1] + rotation[3 * i + 2] * centre[2]));
  return { rotation, translation };
}

export class FaceRenderer {
  // canvas: an HTMLCanvasElement (its size is the output's); model: model.js's Model;
  // hello: the gateway's "hello" JSON (its camera: fx, fy, cx, cy, width, height).
  constructor(canvas, model, hello) {
    const gl = canvas.getContext("webgl2", { antialias: false, depth: true, alpha: false,
                                             premultipliedAlpha: false });
    if (!gl) throw new Error("WebGL2 is not available in this browser");
    if (!gl.getExtension("EXT_color_buffer_float"))
      throw new Error("WebGL2 without EXT_color_buffer_float: the regions' float16 mipmaps " +
                      "cannot be made");
    this.canvas = canvas;
    this.gl = gl;
    this.hello = hello;
    this._positions = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, this._positions);
    gl.bufferData(gl.ARRAY_BUFFER, model.positions.byteLength, gl.DYNAMIC_DRAW);
    this._uv = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, this._uv);
    gl.bufferData(gl.ARRAY_BUFFER, model.uv, gl.STATIC_DRAW);
    this._indices = gl.createBuffer();
    this._vao = gl.createVertexArray();
    gl.bindVertexArray(this._vao);
    gl.bindBuffer(gl.ARRAY_BUFFER, this._positions);
    gl.enableVertexAttribArray(0);
    gl.vertexAttribPointer(0, 3, gl.FLOAT, false, 0, 0);
    gl.bindBuffer(gl.ARRAY_BUFFER, this._uv);
    gl.enableVertexAttribArray(1);
    gl.vertexAttribPointer(1, 2, gl.FLOAT, false, 0, 0);
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, this._indices);
    gl.bindVertexArray(null);
    this._vertexShader = this._shader(gl.VERTEX_SHADER, VERTEX);
    this._texture = this._uploadTexture(model.texture);
    this._programs = [];
    this._volumes = [];
    this.model = null;
    this.setModel(model);
  }

  _shader(kind, source) {
    const gl = this.gl, shader = gl.createShader(kind);
    gl.shaderSource(shader, source);
    gl.compileShader(shader);
    if (!gl.getShaderParameter(shader, gl.COMPILE_STATUS))
      throw new Error(`shader: ${gl.getShaderInfoLog(shader)}`);
    return shader;
  }

  _uploadTexture(texture) {
    const gl = this.gl, { width, height, rgba } = texture;
    const rgb = new Uint8Array(width * height * 3);
    for (let y = 0; y < height; y++) {  // rows bottom first: OpenGL's t is facewire's v
      const from = (height - 1 - y) * width;
      for (let x = 0; x < width; x++)
        for (let c = 0; c < 3; c++) rgb[3 * (y * width + x) + c] = rgba[4 * (from + x) + c];
    }
    const t = gl.createTexture();
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D, t);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGB8, width, height, 0, gl.RGB, gl.UNSIGNED_BYTE, rgb);
    gl.generateMipmap(gl.TEXTURE_2D);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.LINEAR_MIPMAP_LINEAR);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.LINEAR);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
    return t;
  }

  // One area's volume as a mipmapped RGBA16F 2D array texture (receiver/render.py _upload).
  _uploadVolume(volume) {
    const gl = this.gl, t = gl.createTexture();
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D_ARRAY, t);
    gl.texImage3D(gl.TEXTURE_2D_ARRAY, 0, gl.RGBA16F, volume.width, volume.height, volume.k, 0,
                  gl.RGBA, gl.FLOAT, volume.data);
    gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_BASE_LEVEL, 0);
    gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_MAX_LEVEL, MIP_LEVELS);
    gl.generateMipmap(gl.TEXTURE_2D_ARRAY);
    gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_MIN_FILTER, gl.LINEAR_MIPMAP_LINEAR);
    gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_MAG_FILTER, gl.LINEAR);
    gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
    gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
    return t;
  }

  // Another version of the same model (model.js loadUpdate): the regions that changed are
  // uploaded again; when the draw order changed too, the groups and programs are made anew.
  setModel(model) {
    const gl = this.gl, old = this.model;
    if (old && (model.positions !== old.positions || model.texture.width !== old.texture.width ||
                model.texture.height !== old.texture.height))
      throw new Error("setModel: a version of another model; make a new FaceRenderer");
    if (old && model.texture !== old.texture) { // a texture patch (models/patch.py)
      gl.deleteTexture(this._texture);
      this._texture = this._uploadTexture(model.texture);
    }
    const areas = regionAreas(model);
    const layout = areas.map((a) => a.region).join(",");
    if (old && layout === this._layout) {
      areas.forEach(({ region, area }, a) => {
        if (model.regions[region] !== old.regions[region]) {
          gl.deleteTexture(this._volumes[a]);
          this._volumes[a] = this._uploadVolume(area.volume);
        }
      });
    } else {
      this._volumes.forEach((t) => gl.deleteTexture(t));
      this._volumes = areas.map(({ area }) => this._uploadVolume(area.volume));
      this._build(model, areas);
      this._layout = layout;
    }
    this._areas = areas;
    this.model = model;
  }

  // The sorted index buffer and one program per triangle group (receiver/render.py _setup).
  _build(model, areas) {
    const gl = this.gl;
    const { triangles, groups } = triangleGroups(model, areas);
    gl.bindVertexArray(this._vao);
    gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, triangles, gl.STATIC_DRAW);
    gl.bindVertexArray(null);
    this._programs.forEach((g) => gl.deleteProgram(g.program));
    this._programs = groups.map((group) => {
      const program = gl.createProgram();
      gl.attachShader(program, this._vertexShader);
      const shader = this._shader(gl.FRAGMENT_SHADER, fragment(group.areas));
      gl.attachShader(program, shader);
      gl.bindAttribLocation(program, 0, "in_position");
      gl.bindAttribLocation(program, 1, "in_uv");
      gl.linkProgram(program);
      gl.deleteShader(shader);  // freed with the program
      if (!gl.getProgramParameter(program, gl.LINK_STATUS))
        throw new Error(`program: ${gl.getProgramInfoLog(program)}`);
      gl.useProgram(program);
      gl.uniform1i(gl.getUniformLocation(program, "image"), 0);
      const layers = group.areas.map((a) => {
        const [u0, v0, u1, v1] = areas[a].area.padded;
        gl.uniform4f(gl.getUniformLocation(program, `rect${a}`), u0, v0, 1 / (u1 - u0),
                     1 / (v1 - v0));
        gl.uniform1i(gl.getUniformLocation(program, `volume${a}`), 1 + a);
        return { location: gl.getUniformLocation(program, `layer${a}`), area: a };
      });
      return { program, first: 3 * group.first, count: 3 * group.count, layers,
               mvp: gl.getUniformLocation(program, "mvp"),
               shade: gl.getUniformLocation(program, "shade") };
    });
  }

  // The camera's 4x4 row-major projection times view for this state and view.
  _mvp(state, view, width, height) {
    if (!view || view.kind === "camera") {
      const c = this.hello?.camera;
      if (!c || !(c.width > 0 && c.height > 0)) throw new Error("hello: no sender camera");
      const sx = width / c.width, sy = height / c.height;
      const p = projection(c.fx * sx, c.fy * sy, (c.cx + 0.5) * sx - 0.5,
                           (c.cy + 0.5) * sy - 0.5, width, height);
      return multiply(p, poseMatrix(state.rotation, state.translation));
    }
    // receiver/views.py virtual_view with the orbit's angles and distance
    const { centre, fov_deg: fov } = this.model.framing;
    const f = 0.5 * height / Math.tan(fov * Math.PI / 360);
    const p = projection(f, f, (width - 1) / 2, (height - 1) / 2, width, height);
    const orbit = orbitPose(view.yaw, view.pitch, view.distance, centre);
    const r = state.rotation, c = centre;
    const rc = [0, 1, 2].map((i) => r[3 * i] * c[0] + r[3 * i + 1] * c[1] + r[3 * i + 2] * c[2]);
    const head = poseMatrix(r, [c[0] - rc[0], c[1] - rc[1], c[2] - rc[2]]);
    return multiply(p, multiply(poseMatrix(orbit.rotation, orbit.translation), head));
  }

  // Draw one FrameState (page's playout.js) from `view` (views.js; {kind: "camera"} when
  // omitted) into the canvas.
  render(state, view) {
    const gl = this.gl, width = this.canvas.width, height = this.canvas.height;
    const vertices = this.model.rig.morph(state.residuals);
    gl.bindBuffer(gl.ARRAY_BUFFER, this._positions);
    gl.bufferSubData(gl.ARRAY_BUFFER, 0, vertices);
    const mvp = columnMajor(this._mvp(state, view, width, height));
    const layers = this.model.regions.map((r, i) => {
      const k = r.layers;
      const depth = Math.min(Math.max(state.q[i], 0), k - 1);
      const below = Math.floor(depth);
      return [below, Math.min(below + 1, k - 1), depth - below];
    });
    gl.viewport(0, 0, width, height);
    gl.enable(gl.DEPTH_TEST);
    gl.enable(gl.CULL_FACE);  // back faces: the header's "Culling"
    gl.cullFace(gl.BACK);
    gl.frontFace(gl.CCW);
    gl.clearColor(0, 0, 0, 1);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D, this._texture);
    this._volumes.forEach((t, a) => {
      gl.activeTexture(gl.TEXTURE1 + a);
      gl.bindTexture(gl.TEXTURE_2D_ARRAY, t);
    });
    gl.bindVertexArray(this._vao);
    const shade = state.shade ?? [0, 0, 0];
    for (const group of this._programs) {
      gl.useProgram(group.program);
      gl.uniformMatrix4fv(group.mvp, false, mvp);
      gl.uniform3f(group.shade, shade[0], shade[1], shade[2]);
      for (const { location, area } of group.layers)
        gl.uniform3fv(location, layers[this._areas[area].region]);
      gl.drawElements(gl.TRIANGLES, group.count, gl.UNSIGNED_INT, 4 * group.first);
    }
    gl.bindVertexArray(null);
  }

  // Free the GPU objects (before a renderer for another model takes the canvas's context).
  release() {
    const gl = this.gl;
    this._programs.forEach((g) => gl.deleteProgram(g.program));
    this._volumes.forEach((t) => gl.deleteTexture(t));
    gl.deleteTexture(this._texture);
    gl.deleteShader(this._vertexShader);
    [this._positions, this._uv, this._indices].forEach((b) => gl.deleteBuffer(b));
    gl.deleteVertexArray(this._vao);
    this._programs = [];
    this._volumes = [];
  }

  // -> Uint8Array(height * width * 3), RGB, row 0 = top (for tests; call after render, in
  // the same task).
  readPixels() {
    const gl = this.gl, width = this.canvas.width, height = this.canvas.height;
    const rgba = new Uint8Array(width * height * 4);
    gl.readPixels(0, 0, width, height, gl.RGBA, gl.UNSIGNED_BYTE, rgba);
    const out = new Uint8Array(width * height * 3);
    for (let y = 0; y < height; y++) {
      const from = (height - 1 - y) * width;
      for (let x = 0; x < width; x++)
        for (let c = 0; c < 3; c++) out[3 * (y * width + x) + c] = rgba[4 * (from + x) + c];
    }
    return out;
  }
}

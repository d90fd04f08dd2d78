"""The browser's model (models.webmodel) and its WebGL2 renderer (receiver/web/) against Python.

The model's bytes are read back here the way the page reads them (the glb with models.gltf's
reader, the rig's weights rebuilt from the rig file alone, an update applied from its file
alone) and compared with the Python model, rig and versions.
"""

from __future__ import annotations

import dataclasses
import json
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import zip_members

from facewire.models.gltf import read_glb
from facewire.models.modelfile import ModelError, PersonModel, load_model
from facewire.models.patch import TexturePatch, Tile, apply_patch
from facewire.models.rig import Rig
from facewire.models.update import ModelUpdate, apply_update
from facewire.models.webmodel import model_glb, rig_bin, update_bin


def _glb_json(data: bytes) -> dict:
    length = struct.unpack_from("<I", data, 12)[0]
    return json.loads(data[20:20 + length])


def _glb_image(data: bytes, doc: dict, index: int) -> bytes:
    view = doc["bufferViews"][doc["images"][index]["bufferView"]]
    start = 28 + struct.unpack_from("<I", data, 12)[0] + view["byteOffset"]
    return data[start:start + view["byteLength"]]


def _container(data: bytes, magic: bytes) -> tuple[dict, dict[str, np.ndarray], memoryview]:
    """The JSON, arrays and body of a rig or update file (models.webmodel's container)."""
    head, version, length = struct.unpack_from("<4sII", data)
    assert (head, version) == (magic, 1) and (12 + length) % 8 == 0
    header = json.loads(data[12:12 + length])
    body = memoryview(data)[12 + length:]
    arrays = {}
    for name, spec in header.get("arrays", {}).items():
        dtype = np.dtype("<" + spec["dtype"])
        assert spec["offset"] % 8 == 0
        count = int(np.prod(spec["shape"]))
        arrays[name] = np.frombuffer(body, dtype, count, spec["offset"]).reshape(spec["shape"])
    return header, arrays, body


@pytest.fixture(scope="module")
def model(person_model: Path) -> PersonModel:
    return load_model(person_model)


@pytest.fixture(scope="module")
def glb(model: PersonModel) -> bytes:
    return model_glb(model)


def test_the_glb_holds_the_mesh_and_the_model_files_own_pngs(
        model: PersonModel, glb: bytes, person_model: Path, tmp_path: Path) -> None:
    (tmp_path / "m.glb").write_bytes(glb)
    mesh = read_glb(tmp_path / "m.glb")
    assert np.array_equal(mesh.positions, model.mesh.vertices)  # mm, exactly
    assert np.abs(mesh.uv - model.mesh.uv).max() < 1e-7
    assert np.array_equal(mesh.triangles, model.mesh.triangles)
    assert np.array_equal(mesh.texture, model.texture)
    doc = _glb_json(glb)
    assert doc["accessors"][doc["meshes"][0]["primitives"][0]["indices"]]["componentType"] \
        == 5123  # uint16: N < 65536
    members = zip_members(person_model)
    for image in doc["images"]:
        assert _glb_image(glb, doc, doc["images"].index(image)) == members[image["name"]]
    regions = doc["extras"]["facewire"]["regions"]
    assert [r["name"] for r in regions] == [r.name for r in model.regions]
    for meta, region in zip(regions, model.regions, strict=True):
        assert meta["opacity"] == list(region.opacity) and meta["rest"] == region.rest
        for area_meta, area in zip(meta["areas"], region.parts(), strict=True):
            assert tuple(area_meta["uv_rect"]) == area.uv_rect
            mask = cv2.imdecode(np.frombuffer(_glb_image(glb, doc, area_meta["mask"]),
                                              np.uint8), cv2.IMREAD_UNCHANGED)
            assert np.array_equal(mask, area.mask)
    size = len(glb) + len(rig_bin(model))
    assert size <= 1.10 * model.file_bytes, (size, model.file_bytes)


def weights_from_rig_file(data: bytes, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 9) morph weights and (9, 2, 3) tangents from the rig file and the glb's positions
    alone: the page's computation (models.webmodel, "Rig"), in numpy."""
    header, a, _ = _container(data, b"FWRG")
    p = positions.astype(np.float64)
    p[a["lip_vertices"], 1] -= a["lip_drop"]
    r = np.linalg.norm(p[:, None, :] - a["centres"][None], axis=2)
    if header["kernel"] == "multiquadric":
        rows = np.hstack([np.sqrt(r ** 2 + a["shape"] ** 2),
                          header["balance"] * np.hstack([(p - a["origin"]) / header["scale"],
                                                         np.ones((len(p), 1))])])
    else:
        rows = np.exp(-(r / a["shape"]) ** 2)
    weights = rows @ a["z"]
    weights[a["frozen"]] = 0.0
    return weights, a["tangents"]


@pytest.mark.parametrize("kernel", ["multiquadric", "gaussian"])
def test_the_rig_file_gives_the_rigs_weights(model: PersonModel, kernel: str) -> None:
    rig = Rig(model.mesh, kernel=kernel)
    data = rig_bin(model, rig)
    assert len(data) < 40_000
    weights, tangents = weights_from_rig_file(data, model.mesh.vertices)
    assert np.abs(weights - rig.weights).max() < 1e-4
    assert np.array_equal(tangents, rig.tangents)
    uv = np.random.default_rng(1).normal(0.0, 3.0, (9, 2)).astype(np.float32)
    d = np.einsum("kc,kcj->kj", uv, tangents)
    assert np.abs(model.mesh.vertices + weights @ d - rig.morph(rig.from_tangent(uv))).max() \
        < 1e-3


def apply_update_file(data: bytes, previous: PersonModel) -> list[tuple[int, list[np.ndarray],
                                                                         tuple, float]]:
    """Per changed region: (index, its new layer stacks per area, opacity, rest), from the
    update file and the previous version alone."""
    header, _, body = _container(data, b"FWUP")
    out = []
    for change in header["regions"]:
        parts = previous.regions[change["index"]].parts()
        stacks = []
        for n, part in enumerate(parts):
            layers = []
            for state in change["states"]:
                if "from" in state:
                    layers.append(part.layers[state["from"]])
                else:
                    at, length = header["blobs"][state["images"][n]]
                    png = np.frombuffer(body[at:at + length], np.uint8)
                    layers.append(cv2.cvtColor(cv2.imdecode(png, cv2.IMREAD_COLOR),
                                               cv2.COLOR_BGR2RGB))
            stacks.append(np.stack(layers))
        out.append((change["index"], stacks, tuple(change["opacity"]), change["rest"]))
    return out


def learned_version(model: PersonModel) -> PersonModel:
    """The model with a new mouth state inserted at its rest (an update's version 1)."""
    region = next(r for r in model.regions if r.name == "mouth")
    rng = np.random.default_rng(3)
    return apply_update(model, ModelUpdate(
        base_sha256=model.sha256, serial=1, region="mouth", position=round(region.rest),
        replaces=None, template=np.zeros((16, 16), np.float32), opacity=0.8,
        layers=tuple(rng.integers(0, 256, p.layers.shape[1:], dtype=np.uint8)
                     for p in region.parts())))


def test_the_update_file_makes_the_next_version(model: PersonModel) -> None:
    version = learned_version(model)
    data = update_bin(model, version)
    changes = apply_update_file(data, model)
    assert [c[0] for c in changes] == [[r.name for r in model.regions].index("mouth")]
    index, stacks, opacity, rest = changes[0]
    new = version.regions[index]
    assert opacity == new.opacity and rest == new.rest
    for stack, part in zip(stacks, new.parts(), strict=True):
        assert np.array_equal(stack, part.layers)
    header = _container(data, b"FWUP")[0]  # only the new state's images travel
    assert len(header["blobs"]) == len(new.parts())
    assert _container(update_bin(version, version), b"FWUP")[0]["regions"] == []
    with pytest.raises(ModelError, match="not a version of the previous model"):
        update_bin(model, dataclasses.replace(version, texture=version.texture[:-1],
                                              confidence=None))


# ---- the page's modules in real headless Chromium (WebGL2 through SwiftShader) ------------

WIDTH, HEIGHT = 640, 480
FRAMES = 24  # states of the log rendered by both

TEST_PAGE = b"""<!doctype html>
<canvas id="canvas" width="640" height="480"></canvas>
<script type="module">
import * as model from "./model.js";
import * as render from "./render.js";
import * as views from "./views.js";

function state(o) {
  return { ...o, rotation: Float64Array.from(o.rotation),
           translation: Float64Array.from(o.translation),
           residuals: Float32Array.from(o.residuals), q: Float32Array.from(o.q),
           shade: Float32Array.from(o.shade) };
}

function base64(bytes) {
  let text = "";
  for (let i = 0; i < bytes.length; i += 0x8000)
    text += String.fromCharCode.apply(null, bytes.subarray(i, i + 0x8000));
  return btoa(text);
}

async function refused(promise) {
  try {
    await promise;
  } catch (error) {
    return `${error.name}: ${error.message}`;
  }
  return "accepted";
}

window.t = { model, render, views, state, base64, refused };
window.ready = true;
</script>
"""


def _evaluate(browser, session: str, expression: str, timeout: float = 60.0):
    """A JavaScript expression's value in the page (promises awaited), with a timeout long
    enough for loading a model on a loaded machine."""
    result = browser.call("Runtime.evaluate", {"expression": expression, "returnByValue": True,
                                               "awaitPromise": True}, session, timeout=timeout)
    if "exceptionDetails" in result:
        raise RuntimeError(f"page script failed: {result['exceptionDetails']}")
    return result["result"].get("value")


def _state_json(state) -> dict:
    return {"seq": state.seq, "rotation": state.rotation.ravel().tolist(),
            "translation": state.translation.tolist(),
            "residuals": state.residuals.ravel().tolist(), "q": state.q.tolist(),
            "flags": int(state.flags), "status": state.status, "weight": state.weight,
            "arrival_s": state.arrival_s, "serial": state.serial,
            "shade": state.shade.tolist()}


@pytest.fixture(scope="module")
def states(person_model: Path, shared_data: Path, tmp_path_factory: pytest.TempPathFactory):
    """The log's hello and FRAMES of its playout states, evenly spread over lp_d0.mp4."""
    from facewire.protocol.log import read_log
    from facewire.receiver.playout import replay_states
    from facewire.sender.pipeline import encode_video

    path = tmp_path_factory.mktemp("web") / "lp_d0.fwlog"
    encode_video(person_model, shared_data / "video" / "lp_d0.mp4", path, learn=False)
    log = read_log(path)
    played = list(replay_states(log.packets, log.times, log.hello.rate_hz))
    picks = np.linspace(0, len(played) - 1, FRAMES).round().astype(int)
    return log.hello, [played[i] for i in picks]


@pytest.fixture(scope="module")
def page(model: PersonModel, glb: bytes, tmp_path_factory: pytest.TempPathFactory):
    """A Chromium tab on the test page, with the model's files, a version step and corrupt
    copies served beside the page's modules; yields (browser, session)."""
    from browser import WEBGL_FLAGS, DevTools, find_chromium
    from webpage import PageServer, open_tab

    chromium = find_chromium()
    rig = rig_bin(model)
    update = update_bin(model, learned_version(model))
    patch = update_bin(model, patched_version(model))
    binary = "application/octet-stream"
    bad_rig = bytearray(rig)
    header = _container(rig, b"FWRG")[0]
    at = 12 + struct.unpack_from("<I", rig, 8)[0] + header["arrays"]["z"]["offset"]
    bad_rig[at:at + 8] = struct.pack("<d", float("nan"))
    bad_update = bytearray(update)
    body = 12 + struct.unpack_from("<I", update, 8)[0]
    bad_update[body:body + 8] = b"notapng!"  # the new state's first image
    extra = {"/test.html": ("text/html", TEST_PAGE), "/m.glb": (binary, glb),
             "/m.rig": (binary, rig), "/m/1.upd": (binary, update),
             "/m/p1.upd": (binary, patch),
             "/cut.glb": (binary, glb[:len(glb) // 2]), "/nan.rig": (binary, bytes(bad_rig)),
             "/bad.upd": (binary, bytes(bad_update))}
    folder = tmp_path_factory.mktemp("chromium")
    with PageServer(extra) as server:
        browser = DevTools(chromium, folder / "profile", folder / "chromium.log", WEBGL_FLAGS)
        try:
            session = open_tab(browser, server.url + "/test.html", "window.ready === true")
            _evaluate(browser, session, """(async () => {
              window.m = await t.model.loadModel({sha256: "x", glb: "/m.glb", rig: "/m.rig"});
              return true; })()""", timeout=120)
            yield browser, session
        finally:
            browser.close()


def _floats(text: str) -> np.ndarray:
    import base64
    return np.frombuffer(base64.b64decode(text), np.float32)


def test_the_page_morphs_like_the_rig(page, model: PersonModel) -> None:
    browser, session = page
    rig = Rig(model.mesh)
    uv = np.random.default_rng(7).normal(0.0, 4.0, (9, 2)).astype(np.float32)
    got = _floats(_evaluate(browser, session, f"""
        t.base64(new Uint8Array(m.rig.morph(Float32Array.from({uv.ravel().tolist()})).buffer))
        """)).reshape(-1, 3)
    want = rig.morph(rig.from_tangent(uv))
    print(f"page's morph vs Rig.morph: max {np.abs(got - want).max():.2g} mm")
    assert np.abs(got - want).max() < 1e-3  # mm
    assert np.abs(want - model.mesh.vertices).max() > 3.0  # it did move


def _hello_json(hello) -> dict:
    c = hello.camera
    return {"type": "hello", "model_sha256": hello.model_sha256, "rate_hz": hello.rate_hz,
            "camera": {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy, "width": c.width,
                       "height": c.height}}


def _page_frames(browser, session: str, hello, states: list, model_expr: str = "m"
                 ) -> list[np.ndarray]:
    """The page's renderings of ``states`` (one FaceRenderer on the test page's canvas)."""
    import base64
    _evaluate(browser, session, f"""(() => {{
        window.r ??= new t.render.FaceRenderer(document.getElementById("canvas"), m,
                                               {json.dumps(_hello_json(hello))});
        return true; }})()""")
    frames = []
    for state in states:
        text = _evaluate(browser, session, f"""(() => {{
            window.r.setModel({model_expr});
            window.r.render(t.state({json.dumps(_state_json(state))}), {{kind: "camera"}});
            return t.base64(window.r.readPixels()); }})()""")
        frames.append(np.frombuffer(base64.b64decode(text), np.uint8).reshape(HEIGHT, WIDTH, 3))
    return frames


def _face_ssim(rig: Rig, hello, state, a: np.ndarray, b: np.ndarray) -> float:
    """Grey SSIM of two RGB renderings over the face (bench.fidelity's box and mask of the
    state's projected landmarks)."""
    from facewire.bench.fidelity import face_box, face_mask, gray_ssim
    from facewire.receiver.views import sender_view

    camera = sender_view(hello.camera, state.rotation, state.translation, WIDTH, HEIGHT)
    points = camera.project(rig.landmarks(rig.from_tangent(state.residuals)))
    box = face_box(points, WIDTH, HEIGHT)
    x0, y0, x1, y1 = box
    crop = (slice(y0, y1), slice(x0, x1))
    return gray_ssim(a[crop][..., ::-1], b[crop][..., ::-1], face_mask(points, box))


def test_the_page_renders_the_log_like_python(page, model: PersonModel, states,
                                              tmp_path: Path) -> None:
    from facewire.receiver.scene import StateRenderer

    browser, session = page
    hello, played = states
    ours = _page_frames(browser, session, hello, played)
    with StateRenderer(model, WIDTH, HEIGHT, hello.camera) as python:
        theirs = [python.render(s) for s in played]
        rig = python.rig
    ssim = [_face_ssim(rig, hello, s, a, b) for s, a, b in zip(played, ours, theirs,
                                                                strict=True)]
    worst = int(np.argmin(ssim))
    side = tmp_path / "page_vs_python.png"
    cv2.imwrite(str(side), np.hstack([ours[worst], theirs[worst]])[..., ::-1])
    print(f"face SSIM page vs Python: mean {np.mean(ssim):.4f}, min {min(ssim):.4f} "
          f"(frame {worst}: {side})")
    assert np.mean(ssim) >= 0.97, (ssim, side)
    assert all(f.mean() > 5 for f in ours)  # a face in every frame


def test_an_update_renders_like_pythons_version(page, model: PersonModel, states) -> None:
    from facewire.receiver.scene import StateRenderer

    browser, session = page
    hello, played = states
    version = learned_version(model)
    mouth = [r.name for r in model.regions].index("mouth")
    new_state = round(next(r for r in model.regions if r.name == "mouth").rest)
    shown = []
    for s in played[::4]:  # the new mouth state shown (where the mouth is open)
        q = s.q.copy()
        q[mouth] = new_state
        shown.append(dataclasses.replace(s, q=q, serial=1))
    assert _evaluate(browser, session, """(async () => {
        window.m1 = await t.model.loadUpdate(m, {type: "update", serial: 1, url: "/m/1.upd"});
        return [m1.serial, m1.regions.map((r) => r.layers), m.regions.map((r) => r.layers)];
        })()""") == [1, [len(r.layers) for r in version.regions],
                     [len(r.layers) for r in model.regions]]
    ours = _page_frames(browser, session, hello, shown, "m1")
    with StateRenderer(version, WIDTH, HEIGHT, hello.camera) as python:
        theirs = [python.render(s) for s in shown]
        before = StateRenderer(model, WIDTH, HEIGHT, hello.camera)
        try:
            old = [before.render(s) for s in shown]
        finally:
            before.release()
        rig = python.rig
    ssim = [_face_ssim(rig, hello, s, a, b) for s, a, b in zip(shown, ours, theirs, strict=True)]
    before = [_face_ssim(rig, hello, s, a, b) for s, a, b in zip(shown, ours, old, strict=True)]
    shows = [_face_ssim(rig, hello, s, a, b) < 0.99 for s, a, b in zip(shown, theirs, old,
                                                                        strict=True)]
    print(f"update: face SSIM page vs Python's version 1: {np.round(ssim, 4)}; "
          f"vs version 0: {np.round(before, 4)}; where Python's versions differ: {shows}")
    assert min(ssim) >= 0.97
    assert any(shows)
    assert all(b < s - 0.005 for b, s, show in zip(before, ssim, shows, strict=True) if show)


def patched_version(model: PersonModel) -> PersonModel:
    """Version 1 of ``model`` made by a texture patch: the cheek beside the nose, and the
    mouth's side, 80 levels darker (``models.patch``)."""
    h, w = model.texture.shape[:2]
    uv = model.mesh.uv[model.mesh.landmarks].astype(np.float64)
    u, v = uv[31] + 0.35 * (uv[3] - uv[31])
    dark = np.full((16, 16, 3), 108, np.uint8)
    tile = Tile(int((1 - v) * h) - 64, int(u * w) - 64, dark)
    return apply_patch(model, TexturePatch(model.sha256, 1, 8, (tile,)))


def test_a_texture_patch_renders_like_pythons_version(page, model: PersonModel, states
                                                      ) -> None:
    from facewire.receiver.scene import StateRenderer

    browser, session = page
    hello, played = states
    version = patched_version(model)
    assert "texture" in _container(update_bin(model, version), b"FWUP")[0]
    assert _evaluate(browser, session, """(async () => {
        window.p1 = await t.model.loadUpdate(m, {type: "update", serial: 1, url: "/m/p1.upd"});
        return [p1.serial, p1.texture !== m.texture]; })()""") == [1, True]
    shown = [dataclasses.replace(s, serial=1) for s in played[::8]]
    ours = _page_frames(browser, session, hello, shown, "p1")
    with StateRenderer(version, WIDTH, HEIGHT, hello.camera) as python:
        theirs = [python.render(s) for s in shown]
        rig = python.rig
    with StateRenderer(model, WIDTH, HEIGHT, hello.camera) as before:
        old = [before.render(s) for s in shown]
    ssim = [_face_ssim(rig, hello, s, a, b) for s, a, b in zip(shown, ours, theirs, strict=True)]
    unlike = [_face_ssim(rig, hello, s, a, b) for s, a, b in zip(shown, ours, old, strict=True)]
    print(f"patch: face SSIM page vs Python's patched version: {np.round(ssim, 4)}; vs the "
          f"file's: {np.round(unlike, 4)}")
    assert min(ssim) >= 0.97
    assert np.mean(unlike) < np.mean(ssim) - 0.005


def test_corrupt_files_are_refused_and_the_model_kept(page) -> None:
    browser, session = page
    cut, nan, bad_update, skipped, serial = _evaluate(browser, session, """(async () => [
        await t.refused(t.model.loadModel({glb: "/cut.glb", rig: "/m.rig"})),
        await t.refused(t.model.loadModel({glb: "/m.glb", rig: "/nan.rig"})),
        await t.refused(t.model.loadUpdate(m, {serial: 1, url: "/bad.upd"})),
        await t.refused(t.model.loadUpdate(m, {serial: 2, url: "/m/1.upd"})),
        m.serial])()""")
    assert cut.startswith("ModelError: /cut.glb: header says") and "truncated" in cut
    assert nan == "ModelError: /nan.rig: arrays.z: contains NaN or infinity"
    assert bad_update.startswith("ModelError: /bad.upd: regions[0].states[") \
        and "not a PNG" in bad_update, bad_update
    assert skipped == "ModelError: /m/1.upd: serial: update 2 applies to version 1, the model " \
        "is version 0"
    assert serial == 0  # the model it was applied to is untouched


@pytest.mark.parametrize(("kind", "yaw_deg"), [("front", 0.0), ("three-quarter", 35.0)])
def test_the_orbit_view_is_pythons_virtual_view(page, model: PersonModel, states, kind: str,
                                                yaw_deg: float) -> None:
    import base64

    from facewire.models.framing import THREE_QUARTER_YAW_DEG
    from facewire.receiver.scene import StateRenderer

    assert yaw_deg == (THREE_QUARTER_YAW_DEG if kind == "three-quarter" else 0.0)
    browser, session = page
    hello, played = states
    state = played[len(played) // 2]
    _page_frames(browser, session, hello, [])
    text = _evaluate(browser, session, f"""(() => {{
        r.setModel(m);
        r.render(t.state({json.dumps(_state_json(state))}), {{kind: "orbit",
                 yaw: {np.radians(yaw_deg)}, pitch: 0,
                 distance: t.views.framingDistance(m.framing)}});
        return t.base64(r.readPixels()); }})()""")
    ours = np.frombuffer(base64.b64decode(text), np.uint8).reshape(HEIGHT, WIDTH, 3)
    with StateRenderer(model, WIDTH, HEIGHT, hello.camera, view=kind) as python:
        theirs = python.render(state)
    from facewire.bench.fidelity import gray_ssim
    face = theirs.max(axis=2) > 0
    assert 0.05 < face.mean() < 0.9
    assert gray_ssim(ours[..., ::-1], theirs[..., ::-1], face) >= 0.97


def test_dragging_orbits_and_a_double_click_goes_back_to_the_camera(page) -> None:
    browser, session = page
    _evaluate(browser, session, """(() => {
        window.orbit = new t.views.OrbitView(document.getElementById("canvas"));
        return true; })()""")
    assert _evaluate(browser, session, "orbit.view") == {"kind": "camera"}
    for kind, x in (("mousePressed", 300), ("mouseMoved", 340), ("mouseReleased", 340)):
        browser.call("Input.dispatchMouseEvent", {"type": kind, "x": x, "y": 200,
                                                  "button": "left", "buttons": 1,
                                                  "clickCount": 1}, session)
    view = _evaluate(browser, session, "orbit.view")
    assert view["kind"] == "orbit" and view["yaw"] < 0 and view["pitch"] == 0
    browser.call("Input.dispatchMouseEvent", {"type": "mousePressed", "x": 300, "y": 200,
                                              "button": "left", "clickCount": 2}, session)
    browser.call("Input.dispatchMouseEvent", {"type": "mouseReleased", "x": 300, "y": 200,
                                              "button": "left", "clickCount": 2}, session)
    assert _evaluate(browser, session, "orbit.view") == {"kind": "camera"}

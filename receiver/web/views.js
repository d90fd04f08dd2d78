// The page's two kinds of view: the sender's camera, and an orbit around the head with the
// mouse. Mirrors receiver/views.py (sender_view; the orbit is virtual_view's camera with free
// angles and distance, models/infra/raster.py's orbit_pose: yaw 0, pitch 0 in front of the
// face, positive yaw toward the person's left, positive pitch looking down). render.js makes
// the camera of either.
//
// A view is {kind: "camera"} or {kind: "orbit", yaw, pitch, distance} (radians, mm).
// Dragging with the mouse orbits (a canvas width of drag is half a turn of yaw), the wheel
// moves closer or farther, a double click goes back to the sender's camera.

export const DEFAULT_DISTANCE_MM = 770;  // about the framing's distance for an adult head
const MAX_PITCH = 1.4;  // radians: never quite over the top
const MIN_DISTANCE_MM = 150, MAX_DISTANCE_MM = 5000;

export class OrbitView {
  constructor(canvas, distance = DEFAULT_DISTANCE_MM) {
    this.kind = "camera";
    this.yaw = 0;
    this.pitch = 0;
    this.distance = distance;
    let last = null;
    canvas.addEventListener("pointerdown", (event) => {
      last = [event.clientX, event.clientY];
      canvas.setPointerCapture?.(event.pointerId);
    });
    canvas.addEventListener("pointermove", (event) => {
      if (!last) return;
      const scale = Math.PI / Math.max(canvas.clientWidth, 1);
      const dx = event.clientX - last[0], dy = event.clientY - last[1];
      last = [event.clientX, event.clientY];
      if (dx === 0 && dy === 0) return;
      this.kind = "orbit";
      this.yaw -= dx * scale;
      this.pitch = Math.min(Math.max(this.pitch + dy * scale, -MAX_PITCH), MAX_PITCH);
    });
    const release = () => { last = null; };
    canvas.addEventListener("pointerup", release);
    canvas.addEventListener("pointercancel", release);
    canvas.addEventListener("wheel", (event) => {
      event.preventDefault();
      this.kind = "orbit";
      this.distance = Math.min(Math.max(this.distance * Math.exp(event.deltaY * 1e-3),
                                        MIN_DISTANCE_MM), MAX_DISTANCE_MM);
    }, { passive: false });
    canvas.addEventListener("dblclick", () => this.reset());
  }

  // Back to the sender's camera (the orbit starts again from the front).
  reset() {
    this.kind = "camera";
    this.yaw = 0;
    this.pitch = 0;
  }

  get view() {
    return this.kind === "camera" ? { kind: "camera" }
      : { kind: "orbit", yaw: this.yaw, pitch: this.pitch, distance: this.distance };
  }
}

// The distance at which the orbit frames the head as receiver/views.py's virtual views do
// (models/framing.py: the field fills the height of the field of view); `framing` is a
// Model's (model.js).
export function framingDistance(framing) {
  return framing.field / (2 * Math.tan(framing.fov_deg * Math.PI / 360));
}

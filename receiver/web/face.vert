#version 300 es
// The face's vertex shader, for the Python renderer (receiver/render.py) and the page
// (render.js) alike: model-space position (mm) and texture coordinates in; the clip-space
// position (mvp, models/infra/raster.py's camera), the uv and the model-space (x, y) out.
uniform mat4 mvp;
in vec3 in_position;
in vec2 in_uv;
out vec2 v_uv;
out vec2 v_model;
void main() {
    gl_Position = mvp * vec4(in_position, 1.0);
    v_uv = in_uv;
    v_model = in_position.xy;
}

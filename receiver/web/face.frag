#version 300 es
// The face's fragment shader, for the Python renderer (receiver/render.py, whose docstring
// states the compositing) and the page (render.js) alike. A template: each line ending in
// "// each area" stands for one line per region area the program composites, with "#"
// replaced by the area's index (receiver/render.py's fragment_source, render.js's fragment).
precision highp float;
precision highp sampler2DArray;
uniform sampler2D image;
uniform vec3 shade;
uniform sampler2DArray volume#;  // each area
uniform vec4 rect#;  // each area
uniform vec3 layer#;  // each area
in vec2 v_uv;
in vec2 v_model;
out vec4 f_color;

// models/shading.py: the light's gain at the fragment's model-space (x, y), mm
// (SCALE_MM = 100, the log-gain clipped to [LOG_GAIN_MIN, LOG_GAIN_MAX] = [-1, 1]).
float shade_gain(vec2 p) {
    float g = shade.x + shade.y * p.x / 100.0 + shade.z * p.y / 100.0;
    return exp(clamp(g, -1.0, 1.0));
}

// Composite one region area over the colour c. rect: (u0, v0) of the padded rectangle and
// 1 / its size; layer: (i, i + 1 clamped to k - 1, the weight of i + 1).
vec3 over(vec3 c, vec3 base, sampler2DArray volume, vec4 rect, vec3 layer) {
    vec2 st = (v_uv - rect.xy) * rect.zw;
    vec4 s = texture(volume, vec3(st, layer.x));
    if (layer.z > 0.0) {
        s = mix(s, texture(volume, vec3(st, layer.y)), layer.z);
    }
    return c + s.a * (base - c) + s.rgb;
}

void main() {
    vec3 base = texture(image, v_uv).rgb;
    vec3 c = base;
    c = over(c, base, volume#, rect#, layer#);  // each area
    f_color = vec4(c * shade_gain(v_model), 1.0);
}

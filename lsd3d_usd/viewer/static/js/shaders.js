// GLSL ES 3.00 sources. The surfel shaders follow lsd3d_usd/render/reference.py step by step:
// camera-relative disk axes, culling (centre depth outside [near, far], edge-on, opacity below
// 1/255), SH degree 0-2 colour max(0, 0.5 + SH(direction camera -> surfel)), explicit ray-plane
// intersection per pixel, rho = min(u^2 + v^2, 2 |pixel - projected centre|^2), alpha =
// min(0.99, opacity exp(-rho / 2)), dropped below 1/255 or where the hit lies nearer than near.
// Pixel coordinates are the CPU renderer's: x right, y down, pixel centres at +0.5.

const CAMERA = `
uniform mat3 u_rot;      // world -> camera rotation (OpenCV axes: x right, y down, z ahead)
uniform vec3 u_eye;      // camera centre, world
uniform vec4 u_K;        // fx, fy, cx, cy (pixels)
uniform vec2 u_size;     // drawing buffer width, height
uniform vec2 u_clip;     // near, far
vec4 clipFromCamera(vec3 p) {
  float n = u_clip.x, f = u_clip.y;
  return vec4(2.0 * u_K.x / u_size.x * p.x + (2.0 * u_K.z / u_size.x - 1.0) * p.z,
              -2.0 * u_K.y / u_size.y * p.y + (1.0 - 2.0 * u_K.w / u_size.y) * p.z,
              (f + n) / (f - n) * p.z - 2.0 * f * n / (f - n), p.z);
}
`;

export const SURFEL_VS = `#version 300 es
precision highp float;
precision highp int;
precision highp usampler2D;
${CAMERA}
uniform usampler2D u_data;   // TPS texels per surfel, PER_ROW surfels per row
uniform int u_tps;
uniform int u_perRow;
uniform int u_shDegree;      // 0, 1 or 2
uniform int u_colorMode;     // 0 colour, 1 semantic class
uniform vec3 u_classColors[16];
uniform highp usampler2D u_order; // draw position -> global surfel index (back-to-front)
uniform int u_base;          // draw position of this batch's first surfel
uniform int u_points;        // 1: one point sprite per surfel covering its screen rectangle
flat out vec3 v_pc;          // centre, camera space
flat out vec3 v_nf;          // unit normal facing the camera
flat out vec3 v_tu;          // a_u / s_u^2: u = dot(hit, v_tu)
flat out vec3 v_tv;
flat out vec2 v_centre;      // projected centre, pixels
flat out vec4 v_rgba;        // colour, opacity
flat out vec2 v_lo;          // screen rectangle (pixels)
flat out vec2 v_hi;

// Real SH constants (lsd3d_usd/shmath.py; 3DGS order and signs, render/sh.py sh_basis).
const float C0 = 0.28209479177387814;
const float C1 = 0.4886025119029199;
const float C20 = 1.0925484305920792;
const float C21 = -1.0925484305920792;
const float C22 = 0.31539156525252005;
const float C23 = -1.0925484305920792;
const float C24 = 0.5462742152960396;
const float ALPHA_MIN = 1.0 / 255.0;
const float S_MIN = 1e-8;
const float EDGE_COS = 1e-6;

int s8(uint w, uint shift) { int v = int((w >> shift) & 255u); return v >= 128 ? v - 256 : v; }

// Smallest-three quaternion (pack.py encode_quats), without dynamic indexing (slow in
// software renderers).
vec4 quat(uint w) {
  vec3 o = (vec3(float((w >> 2u) & 1023u), float((w >> 12u) & 1023u), float((w >> 22u) & 1023u)) - 511.0)
           * (0.7071067811865476 / 511.0);
  float l = sqrt(max(0.0, 1.0 - dot(o, o)));
  uint big = w & 3u;
  vec4 q = big == 0u ? vec4(l, o) : big == 1u ? vec4(o.x, l, o.yz) : big == 2u ? vec4(o.xy, l, o.z) : vec4(o, l);
  return normalize(q);
}

vec2 proj(vec3 a) { return vec2(u_K.x * a.x / a.z + u_K.z, u_K.y * a.y / a.z + u_K.w); }

// Grow the rectangle [lo, hi] by the edge a -> b of the disk's square clipped to z >= near.
void extend(vec3 a, vec3 b, inout vec2 lo, inout vec2 hi) {
  if (a.z >= u_clip.x) {
    vec2 pa = proj(a);
    lo = min(lo, pa); hi = max(hi, pa);
  }
  if ((a.z - u_clip.x) * (b.z - u_clip.x) < 0.0) {
    vec2 pm = proj(mix(a, b, (u_clip.x - a.z) / (b.z - a.z)));
    lo = min(lo, pm); hi = max(hi, pm);
  }
}

// Unit normal of the edge a -> b pointing away from g (zero for a degenerate edge).
vec2 outward(vec2 a, vec2 b, vec2 g) {
  vec2 e = b - a;
  float l = length(e);
  if (l < 1e-6) return vec2(0.0);
  vec2 n = vec2(e.y, -e.x) / l;
  return dot(n, 0.5 * (a + b) - g) < 0.0 ? -n : n;
}

// Vertex of a surfel's quad: a corner of the screen rectangle, or tighter, of the projected
// square itself with its edges pushed out by the low-pass radius (the disk around the centre
// lies inside), when that square is in front of the camera and smaller than the rectangle.
vec2 quadVertex(vec3 c0, vec3 c1, vec3 c2, vec3 c3, float rl, vec2 lo, vec2 hi, vec2 corner) {
  vec2 px = mix(lo, hi, corner);
  if (min(min(c0.z, c1.z), min(c2.z, c3.z)) >= u_clip.x) {
    vec2 p0 = proj(c0), p1 = proj(c1), p2 = proj(c2), p3 = proj(c3);
    vec2 g = 0.25 * (p0 + p1 + p2 + p3);
    vec2 n01 = outward(p0, p1, g), n12 = outward(p1, p2, g), n23 = outward(p2, p3, g), n30 = outward(p3, p0, g);
    float k0 = 1.0 + dot(n30, n01), k1 = 1.0 + dot(n01, n12), k2 = 1.0 + dot(n12, n23), k3 = 1.0 + dot(n23, n30);
    if (min(min(k0, k1), min(k2, k3)) > 0.2) {
      vec2 q0 = p0 + rl * (n30 + n01) / k0, q1 = p1 + rl * (n01 + n12) / k1;
      vec2 q2 = p2 + rl * (n12 + n23) / k2, q3 = p3 + rl * (n23 + n30) / k3;
      vec2 d02 = q2 - q0, d13 = q3 - q1;
      float area = 0.5 * abs(d02.x * d13.y - d02.y * d13.x);
      if (area < (hi.x - lo.x) * (hi.y - lo.y)) {
        int k = gl_VertexID & 3;   // quad vertices 0, 1, 2, 3 = square corners 0, 1, 3, 2
        px = k == 0 ? q0 : k == 1 ? q1 : k == 2 ? q3 : q2;
      }
    }
  }
  return px;
}

void cull() { gl_Position = vec4(2.0, 2.0, 2.0, 1.0); }

void main() {
  // One point (u_points) or one quad of indexed triangles, 4 vertices, per surfel. No
  // instancing: software renderers run every instance as a separate batch (~10x slower).
  int slot = u_points == 1 ? gl_VertexID : u_base + (gl_VertexID >> 2);
  vec2 corner = vec2(float(gl_VertexID & 1), float((gl_VertexID >> 1) & 1));
  int idx = int(texelFetch(u_order, ivec2(slot & 4095, slot >> 12), 0).r);
  ivec2 at = ivec2((idx % u_perRow) * u_tps, idx / u_perRow);
  uvec4 t0 = texelFetch(u_data, at, 0);
  uvec4 t1 = texelFetch(u_data, at + ivec2(1, 0), 0);
  vec3 p = uintBitsToFloat(t0.xyz);
  vec4 q = quat(t0.w);
  vec2 s = max(unpackHalf2x16(t1.x), vec2(S_MIN));
  vec2 rg = unpackHalf2x16(t1.y);
  vec2 bx = unpackHalf2x16(t1.z);
  float opacity = float((t1.z >> 16u) & 255u) / 255.0;
  int cls = int((t1.z >> 24u) & 255u) - 1;

  vec3 pc = u_rot * (p - u_eye);
  float x = q.x, y = q.y, z = q.z, w = q.w;
  vec3 ax0 = vec3(1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y + w * z), 2.0 * (x * z - w * y));
  vec3 ax1 = vec3(2.0 * (x * y - w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z + w * x));
  vec3 ax2 = vec3(2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y));
  vec3 au = u_rot * ax0 * s.x;
  vec3 av = u_rot * ax1 * s.y;
  vec3 n = u_rot * ax2;
  float cosv = abs(dot(n, pc)) / max(length(pc), 1e-30);
  if (pc.z < u_clip.x || pc.z > u_clip.y || cosv < EDGE_COS || opacity < ALPHA_MIN) { cull(); return; }
  float r2 = 2.0 * log(opacity / ALPHA_MIN);   // rho bound where alpha >= 1/255
  if (r2 <= 0.0) { cull(); return; }
  float r = sqrt(r2);

  vec3 rgb;
  if (u_colorMode == 1) {
    rgb = cls >= 0 && cls < 16 ? u_classColors[cls] : vec3(0.5);
  } else {
    vec3 dc = vec3(rg, bx.x);
    rgb = 0.5 + C0 * dc;
    if (u_shDegree >= 1 && u_tps >= 3) {
      // sh1 block (formats.js): f16 m1 | 9 x i8 band 1 | f16 m2 | 3 x i8 band 2
      uvec4 t2 = texelFetch(u_data, at + ivec2(2, 0), 0);
      float m = unpackHalf2x16(t1.w).x / 127.0;
      vec3 c1 = vec3(s8(t1.w, 16u), s8(t1.w, 24u), s8(t2.x, 0u)) * m;
      vec3 c2 = vec3(s8(t2.x, 8u), s8(t2.x, 16u), s8(t2.x, 24u)) * m;
      vec3 c3 = vec3(s8(t2.y, 0u), s8(t2.y, 8u), s8(t2.y, 16u)) * m;
      vec3 d = normalize(p - u_eye);   // camera -> surfel, world frame
      rgb += -C1 * d.y * c1 + C1 * d.z * c2 - C1 * d.x * c3;
      if (u_shDegree >= 2 && u_tps >= 4) {
        // sh2 block: the other 12 band-2 i8, coefficient then RGB
        uvec4 t3 = texelFetch(u_data, at + ivec2(3, 0), 0);
        float m2 = unpackHalf2x16((t2.y >> 24u) | ((t2.z & 255u) << 8u)).x / 127.0;
        vec3 c4 = vec3(s8(t2.z, 8u), s8(t2.z, 16u), s8(t2.z, 24u)) * m2;
        vec3 c5 = vec3(s8(t3.x, 0u), s8(t3.x, 8u), s8(t3.x, 16u)) * m2;
        vec3 c6 = vec3(s8(t3.x, 24u), s8(t3.y, 0u), s8(t3.y, 8u)) * m2;
        vec3 c7 = vec3(s8(t3.y, 16u), s8(t3.y, 24u), s8(t3.z, 0u)) * m2;
        vec3 c8 = vec3(s8(t3.z, 8u), s8(t3.z, 16u), s8(t3.z, 24u)) * m2;
        float xx = d.x * d.x, yy = d.y * d.y, zz = d.z * d.z;
        rgb += C20 * d.x * d.y * c4 + C21 * d.y * d.z * c5 + C22 * (2.0 * zz - xx - yy) * c6
             + C23 * d.x * d.z * c7 + C24 * (xx - yy) * c8;
      }
    }
    rgb = max(rgb, 0.0);
  }

  // Screen rectangle: the disk's bounding square (radius r) clipped to z >= near and projected,
  // united with the low-pass disk of radius r / sqrt(2) pixels around the projected centre.
  vec2 centre = proj(pc);
  float rl = r * 0.7071067811865476;
  vec2 lo = centre - rl, hi = centre + rl;
  vec3 c0 = pc - r * au - r * av, c1 = pc + r * au - r * av, c2 = pc + r * au + r * av, c3 = pc - r * au + r * av;
  extend(c0, c1, lo, hi); extend(c1, c2, lo, hi); extend(c2, c3, lo, hi); extend(c3, c0, lo, hi);
  lo = max(floor(lo), vec2(0.0));
  hi = min(ceil(hi), u_size);
  if (hi.x <= lo.x || hi.y <= lo.y) { cull(); return; }
  v_lo = lo; v_hi = hi;
  vec2 px;
  if (u_points == 1) {
    px = 0.5 * (lo + hi);
    gl_PointSize = max(hi.x - lo.x, hi.y - lo.y);
  } else {
    px = quadVertex(c0, c1, c2, c3, rl, lo, hi, corner);
  }
  float zn = (u_clip.y + u_clip.x) / (u_clip.y - u_clip.x) - 2.0 * u_clip.y * u_clip.x / ((u_clip.y - u_clip.x) * pc.z);
  gl_Position = vec4(2.0 * px.x / u_size.x - 1.0, 1.0 - 2.0 * px.y / u_size.y, zn, 1.0);

  v_pc = pc;
  v_nf = dot(n, pc) > 0.0 ? -n : n;
  v_tu = au / dot(au, au);
  v_tv = av / dot(av, av);
  v_centre = centre;
  v_rgba = vec4(rgb, opacity);
}
`;

export const SURFEL_FS = `#version 300 es
precision highp float;
uniform vec4 u_K;
uniform vec2 u_size;
uniform vec2 u_clip;
flat in vec3 v_pc;
flat in vec3 v_nf;
flat in vec3 v_tu;
flat in vec3 v_tv;
flat in vec2 v_centre;
flat in vec4 v_rgba;
flat in vec2 v_lo;
flat in vec2 v_hi;
out vec4 o_color;
void main() {
  vec2 pix = vec2(gl_FragCoord.x, u_size.y - gl_FragCoord.y);
  if (any(lessThan(pix, v_lo)) || any(greaterThan(pix, v_hi))) discard;   // point sprites are square
  vec3 ray = vec3((pix.x - u_K.z) / u_K.x, (pix.y - u_K.w) / u_K.y, 1.0);
  float nd = dot(v_nf, ray);
  float tz = dot(v_nf, v_pc) / (abs(nd) > 1e-30 ? nd : 1.0);
  vec3 hit = tz * ray - v_pc;
  float u = dot(hit, v_tu), v = dot(hit, v_tv);
  float r3 = abs(nd) > 1e-30 ? u * u + v * v : 1e30;
  vec2 d = pix - v_centre;
  float r2 = 2.0 * dot(d, d);
  bool use3 = r3 <= r2;
  float rho = use3 ? r3 : r2;
  float z = use3 ? tz : v_pc.z;
  float alpha = min(0.99, v_rgba.a * exp(-0.5 * rho));
  if (alpha < 1.0 / 255.0 || z < u_clip.x) discard;
  o_color = vec4(v_rgba.rgb * alpha, alpha);
}
`;

// Full-screen env background: the CPU renderer's lookup (env/mapping.py direction_to_uv,
// bilinear, longitude wrapping, latitude clamped), per pixel-centre direction, then the far
// field over it (env/farfield.py FarField.apply): a ray from above the plane z = height going
// down (d_z < -1e-6, env.farfield.MIN_DOWN; world direction, before the dome rotation) meets it after
// t = (eye_z - height) / -d_z and sees max(env(d) + (radiance - ground) * T, 0),
// T = exp(-fog * t): the map's ground half re-coloured to the plane's.
export const FULLSCREEN_VS = `#version 300 es
const vec2 P[3] = vec2[3](vec2(-1.0, -1.0), vec2(3.0, -1.0), vec2(-1.0, 3.0));
void main() { gl_Position = vec4(P[gl_VertexID], 0.0, 1.0); }
`;

export const ENV_FS = `#version 300 es
precision highp float;
${CAMERA}
uniform sampler2D u_env;
uniform mat3 u_domeFromWorld;
uniform int u_poleY;
uniform int u_hasEnv;
uniform int u_farField;         // 1: draw the ground beyond the scene
uniform float u_farHeight;      // world z of the plane (m)
uniform vec3 u_farRadiance;     // in the env map's units
uniform vec3 u_farGround;       // the map's own radiance straight down, same units
uniform float u_farFog;         // fog density (1/m)
out vec4 o_color;
const float PI = 3.141592653589793;
void main() {
  if (u_hasEnv == 0) { o_color = vec4(0.0, 0.0, 0.0, 1.0); return; }
  vec2 pix = vec2(gl_FragCoord.x, u_size.y - gl_FragCoord.y);
  vec3 dc = vec3((pix.x - u_K.z) / u_K.x, (pix.y - u_K.w) / u_K.y, 1.0);
  vec3 w = normalize(transpose(u_rot) * dc);   // world direction
  vec3 d = u_domeFromWorld * w;
  if (u_poleY == 1) d = vec3(d.x, -d.z, d.y);
  float lon = atan(d.x, -d.y);
  float u = fract(0.5 - lon / (2.0 * PI));
  float v = 0.5 - asin(clamp(d.z / length(d), -1.0, 1.0)) / PI;
  vec3 c = texture(u_env, vec2(u, v)).rgb;
  float oz = u_eye.z - u_farHeight;
  if (u_farField == 1 && oz > 0.0 && w.z < -1e-6) {
    float T = exp(-max(u_farFog, 0.0) * (oz / -w.z));
    c = max(c + (u_farRadiance - u_farGround) * T, vec3(0.0));
  }
  o_color = vec4(c, 1.0);
}
`;

// Scene-linear -> display: exposure, tone map (render/preview.py tonemap), sRGB encoding.
export const TONEMAP_FS = `#version 300 es
precision highp float;
uniform sampler2D u_hdr;
uniform float u_gain;
uniform int u_method;     // 0 aces, 1 reinhard, 2 clamp
out vec4 o_color;
vec3 srgb(vec3 x) {
  x = clamp(x, 0.0, 1.0);
  return mix(1.055 * pow(x, vec3(1.0 / 2.4)) - 0.055, 12.92 * x, lessThanEqual(x, vec3(0.0031308)));
}
void main() {
  vec3 x = max(texelFetch(u_hdr, ivec2(gl_FragCoord.xy), 0).rgb * u_gain, 0.0);
  vec3 y;
  if (u_method == 0) y = (x * (2.51 * x + 0.03)) / (x * (2.43 * x + 0.59) + 0.14);
  else if (u_method == 1) y = x / (1.0 + x);
  else y = x;
  o_color = vec4(srgb(clamp(y, 0.0, 1.0)), 1.0);
}
`;

// Opaque actor meshes, lit like actors/relight.py with full sun visibility:
// albedo * (E_sh(n) + E_res max(0, n.s)) / E_ref, n the face normal facing the camera.
export const ACTOR_VS = `#version 300 es
precision highp float;
${CAMERA}
uniform mat4 u_model;
in vec3 a_pos;
in vec3 a_color;
out vec3 v_world;
out vec3 v_albedo;
void main() {
  vec4 wp = u_model * vec4(a_pos, 1.0);
  v_world = wp.xyz;
  v_albedo = a_color;
  gl_Position = clipFromCamera(u_rot * (wp.xyz - u_eye));
}
`;

export const ACTOR_FS = `#version 300 es
precision highp float;
uniform vec3 u_eye;
uniform vec3 u_sh[9];
uniform vec3 u_sunDir;
uniform vec3 u_sunResidual;
uniform float u_reference;
in vec3 v_world;
in vec3 v_albedo;
out vec4 o_color;
void main() {
  vec3 n = normalize(cross(dFdx(v_world), dFdy(v_world)));
  if (dot(n, u_eye - v_world) < 0.0) n = -n;
  float x = n.x, y = n.y, z = n.z;
  float b[9] = float[9](0.28209479177387814, -0.4886025119029199 * y, 0.4886025119029199 * z,
                        -0.4886025119029199 * x, 1.0925484305920792 * x * y, -1.0925484305920792 * y * z,
                        0.31539156525252005 * (2.0 * z * z - x * x - y * y), -1.0925484305920792 * x * z,
                        0.5462742152960396 * (x * x - y * y));
  vec3 e = vec3(0.0);
  for (int k = 0; k < 9; k++) e += b[k] * u_sh[k];
  float cosv = u_sunDir.z > 0.0 ? max(dot(n, u_sunDir), 0.0) : 0.0;
  e = max(e, 0.0) + u_sunResidual * cosv;
  o_color = vec4(v_albedo * e / u_reference, 1.0);
}
`;

// Overlays, drawn after tone mapping: coloured lines and translucent proxy meshes.
export const OVERLAY_VS = `#version 300 es
precision highp float;
${CAMERA}
in vec3 a_pos;
in vec4 a_color;
out vec4 v_color;
out vec3 v_world;
void main() {
  v_color = a_color;
  v_world = a_pos;
  gl_Position = clipFromCamera(u_rot * (a_pos - u_eye));
}
`;

export const OVERLAY_FS = `#version 300 es
precision highp float;
uniform int u_shade;       // 1: flat-shade by the face normal (proxy meshes)
uniform float u_alpha;
uniform vec3 u_eye;
in vec4 v_color;
in vec3 v_world;
out vec4 o_color;
void main() {
  vec3 c = v_color.rgb;
  if (u_shade == 1) {
    vec3 n = normalize(cross(dFdx(v_world), dFdy(v_world)));
    float l = abs(dot(n, normalize(u_eye - v_world)));
    c = pow(c, vec3(1.0 / 2.2)) * (0.45 + 0.55 * l);
  }
  o_color = vec4(c * u_alpha, u_alpha);
}
`;

// EWA surface splatting (Zwicker, Pfister, van Baar & Gross 2001), OpenGL backend of `ewa`.
// The equations are stated in ewa.py; every line below mirrors ewa_kernels.setup_splats and
// rasterize_tiles so that the CPU and GL backends differ only in floating-point rounding.
// One source, passes chosen by #define:
//   PASS_VISIBILITY  the narrow visibility footprint N = J V J^T + v^2 I: per pixel the splat
//                    plane's eye depth (clamped) + z_t and 1 - its coverage, MIN-blended into
//                    the visibility target
//   PASS_BACK        the nearest plane depth behind the visible surface (MIN-blended): the
//                    depth of the back layer
//   PASS_ATTRIBUTE   the resampling filter rho(x) = |det J| / sqrt(det M) exp(-1/2 x^T M^-1 x),
//                    M = J V J^T + l^2 I: (w rgb, w) and (w n, w z) additively blended into
//                    the front layer for fragments no farther than the visibility depth, into
//                    the back layer for those within z_t of the back layer's depth
//   PASS_CATEGORY    categorical colour modes: the packed (weight, palette index) of the same
//                    fragments, MAX-blended per layer into (front, back) (colors.glsl)
// Each splat is an instanced 4-vertex strip covering the pixel box of its cut-off ellipse;
// the conic is evaluated per fragment at the pixel centre.
#include "common.glsl"

uniform float u_radius_scale;
uniform float u_sigma2;           // V = sigma^2 I, in semi-axis units
uniform float u_lowpass2;         // L = l^2 I, render-target pixels squared
uniform float u_vis2;             // v^2 of the visibility footprint
uniform float u_cutoff2;          // R^2: the kernel is cut where x^T M^-1 x > R^2
uniform float u_depth_offset;     // z_t as a fraction of the splat radius
uniform float u_depth_clamp;      // cap of the plane-depth offset, in splat radii
uniform int u_backface_culling;
uniform sampler2D u_visibility;   // nearest depth + z_t per pixel
uniform sampler2D u_back;         // PASS_ATTRIBUTE: the back layer's depth per pixel

#ifdef VERTEX_SHADER
#include "splat_attributes.glsl"
flat out vec2 v_mean;      // m_k, image pixels (y down)
flat out vec3 v_conic;     // (a, b, c) of a dx^2 + 2 b dx dy + c dy^2: M^-1 or N^-1 by pass
flat out vec4 v_depth;     // eye depth at the centre, its pixel gradient (gx, gy), clamp
flat out float v_threshold;  // z_t
flat out vec3 v_clip0;     // clip lines as pixel half-planes a dx + b dy <= c around m_k
flat out vec3 v_clip1;
#ifndef PASS_VISIBILITY
flat out float v_scale;    // |det J| / sqrt(det M)
flat out vec3 v_color;
flat out vec3 v_normal;    // eye space, facing the camera
flat out vec4 v_inv_j;     // J^-1 (column-major): pixel offsets to local coordinates (u, v)
flat out vec3 v_field_u;   // the Phong normal field's eye-space slopes alpha u^, beta v^
flat out vec3 v_field_v;
flat out vec3 v_eye;       // the splat's centre in eye space
#endif

vec3 pixel_half_plane(vec3 line, float j00, float j01, float j10, float j11, float det_j) {
    if (abs(det_j) <= 1e-12 || line.z >= 1.0) return vec3(0.0, 0.0, 1.0);  // edge-on or inactive
    float inv_det = 1.0 / (det_j * u_radius_scale);
    return vec3((line.x * j11 - line.y * j10) * inv_det, (line.y * j00 - line.x * j01) * inv_det, line.z);
}

void cull() {
    gl_Position = vec4(2.0, 2.0, 2.0, 1.0);  // outside the clip volume: no fragments
}

void main() {
    const vec2 corners[4] = vec2[4](vec2(0.0, 0.0), vec2(1.0, 0.0), vec2(0.0, 1.0), vec2(1.0, 1.0));
    vec3 e = (u_view * vec4(in_center, 1.0)).xyz;
    float d = -e.z;
    if (u_ortho <= 0.0 && d <= u_depth_range.x) { cull(); return; }  // J meaningless behind the camera
    if (in_clip0.z < -1.0 || in_clip1.z < -1.0) { cull(); return; }  // clipped away whole (on a crease)
    mat3 rot = mat3(u_view);
    vec3 n = rot * in_normal;
    vec3 u = u_radius_scale * (rot * in_axis_u);
    vec3 v = u_radius_scale * (rot * in_axis_v);
    face_camera(e, n, u, v);  // as ewa_kernels.setup_splats
    float facing = u_ortho > 0.0 ? n.z : -dot(n, e);
    float flip = 1.0;
    if (facing < 0.0) {
        if (u_backface_culling != 0) { cull(); return; }
        n = -n;
        flip = -1.0;  // the normal field turns with the normal
    }
    // J = dproject/deye (2x3) times [u v] (3x2): local tangent coordinates -> pixels.
    vec2 m;
    float j00, j01, j10, j11;
    if (u_ortho > 0.0) {
        m = vec2(u_intrinsics.z + u_ortho * e.x, u_intrinsics.w - u_ortho * e.y);
        j00 = u_ortho * u.x; j01 = u_ortho * v.x;
        j10 = -u_ortho * u.y; j11 = -u_ortho * v.y;
    } else {
        float inv = 1.0 / d;
        m = vec2(u_intrinsics.z + u_intrinsics.x * e.x * inv, u_intrinsics.w - u_intrinsics.y * e.y * inv);
        float a0 = u_intrinsics.x * inv, a2 = u_intrinsics.x * e.x * inv * inv;
        float b1 = -u_intrinsics.y * inv, b2 = -u_intrinsics.y * e.y * inv * inv;
        j00 = a0 * u.x + a2 * u.z; j01 = a0 * v.x + a2 * v.z;
        j10 = b1 * u.y + b2 * u.z; j11 = b1 * v.y + b2 * v.z;
    }
    // M = J V J^T + L.
    float m00 = u_sigma2 * (j00 * j00 + j01 * j01) + u_lowpass2;
    float m01 = u_sigma2 * (j00 * j10 + j01 * j11);
    float m11 = u_sigma2 * (j10 * j10 + j11 * j11) + u_lowpass2;
    float det_m = m00 * m11 - m01 * m01;
    float det_j = j00 * j11 - j01 * j10;
    // Pixel box of the cut ellipse (inclusive pixel indices), clamped to the image.
    float cutoff = sqrt(u_cutoff2);
    vec2 half_size = cutoff * sqrt(vec2(m00, m11));
    vec2 lo = max(ceil(m - half_size - 0.5), vec2(0.0));
    vec2 hi = min(floor(m + half_size - 0.5), u_viewport - 1.0);
    if (lo.x > hi.x || lo.y > hi.y) { cull(); return; }
    // Eye depth on the splat plane, linear in the pixel offset: h J^-1, h = d depth/d(s, t).
    float h0 = -u.z, h1 = -v.z;
    vec2 g = abs(det_j) > 1e-12 ? vec2(h0 * j11 - h1 * j10, h1 * j00 - h0 * j01) / det_j : vec2(0.0);
    float radius = max(length(u), length(v));
    // The visibility footprint N = J V J^T + v^2 I, and the plane's depth range over its cut
    // ellipse, capped so that an edge-on splat (J near singular) cannot claim absurd depths.
    float n00 = m00 - u_lowpass2 + u_vis2, n11 = m11 - u_lowpass2 + u_vis2;
    float det_n = n00 * n11 - m01 * m01;
    float dz = min(cutoff * sqrt(g.x * g.x * n00 + 2.0 * g.x * g.y * m01 + g.y * g.y * n11), u_depth_clamp * radius);
    // A clip line a s + b t <= c of the local coordinates (s, t) = J^-1 dx / radius_scale
    // becomes the pixel half-plane (a, b) adj(J) dx / (det J radius_scale) <= c.
    v_clip0 = pixel_half_plane(in_clip0, j00, j01, j10, j11, det_j);
    v_clip1 = pixel_half_plane(in_clip1, j00, j01, j10, j11, det_j);
    v_mean = m;
    v_depth = vec4(d, g, dz);
    // z_t widened by the depth range, so one splat's extrapolated fringe cannot hide its
    // neighbours; where another layer lies close, no farther than the layer's thickness.
    v_threshold = layer_offset(u_depth_offset * radius + dz, e, normalize(n), in_thickness);
#ifdef PASS_VISIBILITY
    v_conic = vec3(n11, -m01, n00) / det_n;
#else
    v_conic = vec3(m11, -m01, m00) / det_m;
    v_scale = abs(det_j) / sqrt(det_m);
    v_color = in_color;
    v_normal = n;
    v_inv_j = abs(det_j) > 1e-12 ? vec4(j11, -j10, -j01, j00) / det_j : vec4(0.0);
    // the field's tilts at the drawn rim, u_radius_scale times as far as the fitted one
    v_field_u = flip * u_radius_scale * in_field.x * u / max(length(u), 1e-30);
    v_field_v = flip * u_radius_scale * in_field.y * v / max(length(v), 1e-30);
    v_eye = e;
#endif
    // The quad spans the box's pixels edge to edge, so exactly their centres are rasterized.
    gl_Position = image_to_clip(mix(lo, hi + 1.0, corners[gl_VertexID]));
}
#endif

#ifdef FRAGMENT_SHADER
flat in vec2 v_mean;
flat in vec3 v_conic;
flat in vec4 v_depth;
flat in float v_threshold;
flat in vec3 v_clip0;
flat in vec3 v_clip1;
#ifndef PASS_VISIBILITY
flat in float v_scale;
flat in vec3 v_color;
flat in vec3 v_normal;
flat in vec4 v_inv_j;
flat in vec3 v_field_u;
flat in vec3 v_field_v;
flat in vec3 v_eye;
#endif

// Offset of the pixel centre from m_k, the conic's value there (discards beyond the cutoff
// and the clip lines), and the clamped plane depth.
vec2 offset;
float quadric;
float plane_depth() {
    offset = image_coord(gl_FragCoord.xy) - v_mean;
    quadric = v_conic.x * offset.x * offset.x + 2.0 * v_conic.y * offset.x * offset.y
              + v_conic.z * offset.y * offset.y;
    if (quadric > u_cutoff2) discard;
    if (dot(v_clip0.xy, offset) > v_clip0.z || dot(v_clip1.xy, offset) > v_clip1.z) discard;  // beyond a sharp feature
    return v_depth.x + clamp(dot(v_depth.yz, offset), -v_depth.w, v_depth.w);
}

#ifdef PASS_VISIBILITY
// How much of the pixel the splat covers (ewa_kernels._coverage): 0.5 plus the pixel distance
// to the rim sqrt(q) = COVERAGE_SIGMAS of its footprint's ellipse, clamped to [0, 1].
const float COVERAGE_SIGMAS = 1.0;
float coverage() {
    float slope = length(vec2(v_conic.x * offset.x + v_conic.y * offset.y,
                              v_conic.y * offset.x + v_conic.z * offset.y));
    float root = sqrt(quadric);
    if (slope <= 1e-20 * root) return 1.0;  // at the centre
    return clamp(0.5 + (COVERAGE_SIGMAS - root) * root / slope, 0.0, 1.0);
}

layout(location = 0) out vec4 out_depth;
void main() {
    float depth = plane_depth() + v_threshold;
    out_depth = vec4(depth, 1.0 - coverage(), 0.0, 0.0);  // MIN blending: the nearest, the most covering
}
#endif

#ifdef PASS_BACK
layout(location = 0) out vec4 out_depth;
void main() {
    float z = plane_depth();
    if (z <= texelFetch(u_visibility, ivec2(gl_FragCoord.xy), 0).r) discard;  // the front layer
    out_depth = vec4(z, 0.0, 0.0, 0.0);  // MIN blending: the nearest behind the front
}
#endif

#ifdef PASS_CATEGORY
layout(location = 0) out vec4 out_category;  // (front layer, back layer), MAX-blended
void main() {  // the attribute pass's fragments and weights
    float z = plane_depth();
    bool front = z <= texelFetch(u_visibility, ivec2(gl_FragCoord.xy), 0).r;
    if (!front && z > texelFetch(u_back, ivec2(gl_FragCoord.xy), 0).r + v_threshold) discard;
    float category = category_pack(v_scale * exp(-0.5 * quadric), category_index(v_color));
    out_category = front ? vec4(category, -1.0, 0.0, 0.0) : vec4(-1.0, category, 0.0, 0.0);
}
#endif

#ifdef PASS_ATTRIBUTE
layout(location = 0) out vec4 out_color;        // front layer (w rgb, w)
layout(location = 1) out vec4 out_normal;       // front layer (w n, w z)
layout(location = 2) out vec4 out_back_color;   // back layer (w rgb, w)
layout(location = 3) out vec4 out_back_normal;  // back layer (w n, w z)
void main() {
    float z = plane_depth();
    ivec2 texel = ivec2(gl_FragCoord.xy);
    bool front = z <= texelFetch(u_visibility, texel, 0).r;
    if (!front && z > texelFetch(u_back, texel, 0).r + v_threshold) discard;  // behind both layers
    float w = v_scale * exp(-0.5 * quadric);
    // The linear normal field (Botsch, Spernat & Kobbelt 2004, eq. 8) at the local coordinates
    // (u, v) = J^-1 offset, kept within the rim (zero slopes: the splat's own normal).
    vec2 uv = mat2(v_inv_j) * offset;
    uv /= max(length(uv), 1.0);
    vec3 n = field_normal(v_normal + uv.x * v_field_u + uv.y * v_field_v, v_eye);
    vec4 color = vec4(w * v_color, w);
    vec4 normal = vec4(w * n, w * z);
    out_color = front ? color : vec4(0.0);
    out_normal = front ? normal : vec4(0.0);
    out_back_color = front ? vec4(0.0) : color;
    out_back_normal = front ? vec4(0.0) : normal;
}
#endif
#endif

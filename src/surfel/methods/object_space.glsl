// Object-space EWA surface splatting with textured quads (Ren, Pfister & Zwicker 2002; survey 2.1.2).
// One source, passes chosen by #define:
//   PASS_VISIBILITY  a square of side 2 r per surfel in its tangent plane; eye depth + z_t,
//                    MIN-blended into a float target: the visibility ("z") buffer
//   PASS_ATTRIBUTE   one textured quad per surfel shaped by the resampling filter M_k
//                    (eqs. 3-5), Gaussian alpha texture times 1/(r0 r1) (eq. 4), additive
//                    blending of fragments no farther than the visibility depth
//   PASS_CATEGORY    categorical colour modes: the packed (weight, palette index) of the
//                    attribute pass's fragments, MAX-blended (colors.glsl)
//   PASS_NORMALIZE   full-screen: G-buffer from the accumulated sums, deferred shading
// Variant: CLIP_LINES (surfels cut at sharp features by the clip lines of surfel.preprocess).
// Variant: PER_SURFEL_NORMALIZATION (the paper: weights pre-scaled per surfel by in_weight,
// colours not divided per pixel) or per-pixel normalization (Botsch & Kobbelt 2003: divide
// by the accumulated weight).
#include "common.glsl"
#include "shading.glsl"
#include "passes.glsl"

#define MAX_EXTENT 16.0   // splat radii: bound on the filter's object-space std (grazing views)

uniform float u_radius_scale;
uniform float u_depth_offset;     // z_t as a fraction of the splat radius
uniform float u_kernel_std;       // reconstruction kernel std as a fraction of the splat radius
uniform float u_cutoff;           // c: the kernel is cut off at |y| = c standard deviations
uniform float u_lowpass_std;      // screen-space low-pass std in render-target pixels
uniform int u_backface_culling;
uniform sampler2D u_kernel;       // exp(-y.y/2) over the quad, zero beyond the cutoff

#ifdef VERTEX_SHADER
#ifndef PASS_NORMALIZE
#include "splat_attributes.glsl"
#ifdef PER_SURFEL_NORMALIZATION
in float in_weight;          // 1 / (sum of the neighbouring kernels at this surfel's centre)
#endif
out float v_depth;           // eye depth, interpolated perspective-correctly over the planar quad
out vec2 v_texcoord;         // v of eq. 5
#ifdef CLIP_LINES
out vec2 v_local;            // the point in splat coordinates (1 on the rim of the unscaled splat)
flat out vec3 v_clip0;       // clip lines at sharp features, in those coordinates
flat out vec3 v_clip1;
#endif
flat out vec3 v_normal;      // eye space, facing the camera
flat out vec3 v_color;      // encoded (colors.glsl)
flat out float v_alpha;      // the constant 1/(r0 r1) of eq. 4 times the surfel's weight

// Jacobian of the local tangent parameterisation (s, t) to image pixels at eye point c:
// columns are d(x, y)/ds and d(x, y)/dt of the perspective (or orthographic) projection.
mat2 tangent_jacobian(vec3 c, vec3 s, vec3 t) {
    if (u_ortho > 0.0) return u_ortho * mat2(s.x, -s.y, t.x, -t.y);
    float w = -c.z;
    vec2 f = u_intrinsics.xy / (w * w);
    return mat2(f.x * (s.x * w + c.x * s.z), -f.y * (s.y * w + c.y * s.z),
                f.x * (t.x * w + c.x * t.z), -f.y * (t.y * w + c.y * t.z));
}

void main() {
    const vec2 corners[4] = vec2[4](vec2(0.0, 0.0), vec2(1.0, 0.0), vec2(0.0, 1.0), vec2(1.0, 1.0));
    vec2 v = corners[gl_VertexID];
    vec3 c = (u_view * vec4(in_center, 1.0)).xyz;
    vec3 n = mat3(u_view) * in_normal;
    vec3 au = mat3(u_view) * in_axis_u * u_radius_scale;
    vec3 av = mat3(u_view) * in_axis_v * u_radius_scale;
    if (!face_camera(c, n, au, av)) n = normalize(n);
    bool back = faces_away(c, n);
    if (back) n = -n;
    float radius = max(length(au), length(av));
    bool before_near = u_ortho == 0.0 && -c.z < u_depth_range.x;  // the Jacobian degenerates
    if ((back && u_backface_culling != 0) || radius <= 0.0 || before_near) {
        gl_Position = vec4(2.0, 2.0, 2.0, 1.0);  // outside the clip volume: no fragments
        return;
    }
#ifdef PASS_VISIBILITY
    // The square of side twice the splat radius (the largest neighbour distance), pushed
    // back along the viewing ray by z_t (capped by the layer's thickness).
    vec3 p = c + (2.0 * v.x - 1.0) * au + (2.0 * v.y - 1.0) * av;
    v_depth = -p.z + layer_offset(u_depth_offset * radius, c, n, in_thickness);
#ifdef CLIP_LINES
    v_local = (2.0 * v - 1.0) * u_radius_scale;
#endif
#else
    // Orthonormal tangent frame (s, t) and the reconstruction variance V_k in it.
    vec3 s = normalize(au);
    vec3 t = normalize(av - dot(av, s) * s);
    vec2 sigma = u_kernel_std * vec2(length(au), length(av));
    mat2 V = mat2(sigma.x * sigma.x, 0.0, 0.0, sigma.y * sigma.y);
    // The screen-space low-pass (variance u_lowpass_std^2 I) mapped into the tangent plane:
    // J^-1 (std^2 I) J^-T = std^2 (J^T J)^-1. Edge-on splats make J^T J singular; the
    // eigenvalue clamp below bounds the quad then.
    mat2 J = tangent_jacobian(c, s, t);
    mat2 G = transpose(J) * J;
    float det = max(G[0][0] * G[1][1] - G[0][1] * G[1][0], 1e-30);
    mat2 M = V + (u_lowpass_std * u_lowpass_std / det) * mat2(G[1][1], -G[0][1], -G[1][0], G[0][0]);
    // Eigen-decomposition M = Rot(theta) diag(r0^2, r1^2) Rot(theta)^T (eq. 3).
    float mean = 0.5 * (M[0][0] + M[1][1]);
    float half_diff = 0.5 * (M[0][0] - M[1][1]);
    float root = sqrt(half_diff * half_diff + M[0][1] * M[0][1]);
    float limit = MAX_EXTENT * radius;
    float r0 = min(sqrt(mean + root), limit);
    float r1 = min(sqrt(max(mean - root, 1e-30)), limit);
    float theta = 0.5 * atan(2.0 * M[0][1], M[0][0] - M[1][1]);
    mat2 rot = mat2(cos(theta), sin(theta), -sin(theta), cos(theta));
    // Texture coordinates to the unit-Gaussian domain, y in [-c, c]^2 (eq. 5, with c counted
    // in standard deviations of y), then to the tangent plane (eq. 3) and eye space.
    vec2 y = 2.0 * u_cutoff * (v - 0.5);
    vec2 u = rot * (vec2(r0, r1) * y);
    vec3 p = c + u.x * s + u.y * t;
    v_depth = -p.z;
#ifdef CLIP_LINES
    v_local = u_radius_scale * vec2(dot(p - c, au) / dot(au, au), dot(p - c, av) / dot(av, av));
#endif
#ifdef PER_SURFEL_NORMALIZATION
    v_alpha = in_weight / (r0 * r1);
#else
    v_alpha = 1.0 / (r0 * r1);
#endif
#endif
    v_texcoord = v;
#ifdef CLIP_LINES
    v_clip0 = in_clip0;
    v_clip1 = in_clip1;
#endif
    v_normal = n;
    v_color = in_color;
    gl_Position = u_projection * vec4(p, 1.0);
}
#endif
#endif

#ifdef FRAGMENT_SHADER
#ifndef PASS_NORMALIZE
in float v_depth;
in vec2 v_texcoord;
#ifdef CLIP_LINES
in vec2 v_local;
flat in vec3 v_clip0;
flat in vec3 v_clip1;
#endif
flat in vec3 v_normal;
flat in vec3 v_color;
flat in float v_alpha;
#endif

#ifdef PASS_VISIBILITY
layout(location = 0) out vec4 out_depth;
void main() {
    // Coverage of the disk inscribed in the square, cut at its clip lines.
#ifdef CLIP_LINES
    float clipped = clip_excess(v_local, v_clip0, v_clip1);
#else
    float clipped = -1.0;
#endif
    float rho = max(length(2.0 * v_texcoord - 1.0), 1.0 + clipped);
    float coverage = clamp(0.5 + edge_distance(rho), 0.0, 1.0);
    if (clipped > 0.0) discard;  // the square ends at sharp features
    out_depth = vec4(v_depth, 1.0 - coverage, 0.0, 0.0);  // MIN blending: nearest, most covering
}
#endif

#ifdef PASS_ATTRIBUTE
layout(location = 0) out vec4 out_color;   // (w rgb, w)
layout(location = 1) out vec4 out_normal;  // (w n, w z)
void main() {
#ifdef CLIP_LINES
    if (clip_excess(v_local, v_clip0, v_clip1) > 0.0) discard;  // beyond a sharp feature
#endif
    if (v_depth > texelFetch(u_visibility, ivec2(gl_FragCoord.xy), 0).r) discard;  // occluded
    float w = v_alpha * texture(u_kernel, v_texcoord).r;
    out_color = vec4(w * v_color, w);
    out_normal = vec4(w * v_normal, w * v_depth);
}
#endif

#ifdef PASS_CATEGORY
layout(location = 0) out vec4 out_category;
void main() {  // the attribute pass's fragments and weights
#ifdef CLIP_LINES
    if (clip_excess(v_local, v_clip0, v_clip1) > 0.0) discard;
#endif
    if (v_depth > texelFetch(u_visibility, ivec2(gl_FragCoord.xy), 0).r) discard;
    float w = v_alpha * texture(u_kernel, v_texcoord).r;
    out_category = vec4(category_pack(w, category_index(v_color)), -1.0, 0.0, 0.0);
}
#endif

#ifdef PASS_NORMALIZE
void main() {
    Accumulated a;
    if (!fetch_accumulated(0, a)) return;
#ifdef PER_SURFEL_NORMALIZATION
    // The paper's frame buffer holds sum(w rgb) as it is (weights pre-normalized to sum to
    // about one), which already fades with coverage at the silhouette: the straight colour
    // is that divided by the coverage.
    vec3 albedo = blended_albedo(a.weighted_color / max(a.coverage, 1e-3));
    if (a.category >= 0) albedo = table_entry(a.category);
#else
    vec3 albedo = pixel_albedo(a);
#endif
    write_gbuffer(shade(u_shading, albedo, a.normal, a.depth, u_depth_range.x, u_depth_range.y), a);
}
#endif
#endif

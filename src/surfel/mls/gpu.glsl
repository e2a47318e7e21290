// GPU ray casting of the MLS point set surface (Tejada, Gois, Nonato, Castelo & Ertl 2006;
// survey section 2.3.2). One source, the passes chosen by #define (see gpu.py for the flow):
//   PASS_INTERSECT   discs of the bounding spheres: pixel ray meets the point's polynomial,
//                    the nearest t kept by the depth test, with the sample's normal as the
//                    reference normal n_r of the fits to come (on a retry: the nearest beyond
//                    the candidate the pixel's fits failed from)
//   PASS_CULL        full screen: each pixel's depth from its hit's t, 0 where it has none, so
//                    that no support disc reaches the fragment shader there (after the
//                    intersections, and for the kept hits before the shading normal's passes)
//   PASS_MEANS       discs of the kernel supports: weighted sums about the hit point r
//   PASS_FRAME       full screen: weighted mean q, weighted mean normal n of the samples,
//                    local kernel width l and the half-disc offset
//   PASS_SYSTEM      discs of the kernel supports: moments of the quadratic's normal equations
//   PASS_SOLVE       full screen: solve the 6x6 system, re-intersect the ray with the quadratic;
//                    with SHADING_NORMAL: the gradient at the kept hit of the fit that passes 2
//                    to 4 made there under the shading weights (surface.py: shading normal),
//                    written over the kept normal where that fit succeeds
//   PASS_KEEP        full screen: the candidate's surface point, normal and colour where it
//                    converged
//   PASS_RETRY       full screen: the t of the candidate where its fits failed, for the next one
//   PASS_SHADE       full screen: normal, colour and depth into the G-buffer layout
// The weights are surface.py's: w = exp(-|p - r|^2 / h^2 - |n_i - n_r|^2 / sigma_n^2
// - (n_i . (r - p))^2 / (sigma_r h)^2) within SUPPORT h. Sums over a support are in units of
// u_scale (the median kernel width), a fit's frame in units of its local width l, like surface.py.
#include "common.glsl"
#include "shading.glsl"

#define SUPPORT 2.5
#define FAR 3.0e38
#define MISS 1.0e38
// The last of the fixed projection steps keeps its hit only within this many local widths of
// its fit: the CPU tracer iterates until its tolerance (raytrace.TOLERANCE), and a ray that
// passes a coarse part's surface in the air between its rings settles nowhere
#define LAST_HEIGHT 0.1
#define RETRY_GAP 0.5  // a later candidate lies this many of its sampling's kernel widths beyond a failed one

uniform mat4 u_view_inv;        // eye to local world
uniform float u_scale;          // median kernel width: the unit of the support sums
uniform float u_domain;         // domain test / bounding sphere radius in units of the spacing s_i
uniform float u_normal_weight;  // 1 / sigma_n^2
uniform float u_residual_weight;  // 1 / sigma_r^2
uniform float u_boundary;       // half-disc test: largest offset of the weighted mean, in units of l
uniform float u_edge_cos;       // extent test: a sheet's samples have normals within this cosine of the fit's
uniform float u_edge_lateral;   // ... and lie within this many local widths of the line from r along `away`
uniform float u_ridge;          // regularisation of a singular quadratic fit, in units of sum w (surface.RIDGE)
uniform float u_min_neighbours; // facing samples a fit needs in its support (surface.MIN_NEIGHBOURS)
uniform float u_tolerance;      // converged: r within this many local widths of its fit (raytrace.TOLERANCE)
uniform bool u_last;            // the last iteration: apply the half-disc and extent tests to its fit
uniform bool u_update_reference;  // the fit's normal becomes the next reference normal
uniform bool u_retry;           // a later candidate: the nearest beyond the one that failed
// r: t of the candidate the pixel's fits failed from (>= MISS: none); g: 1 there, else 0, on
// every mip level of a power-of-two texture: the mean over each texel's pixels
uniform sampler2D u_failed;

// Three vec4 per point: (p_i, h_i), (colour, s_i), (n_i, h_scale m_i) (surface.MLSSurface.density_width).
layout(std430, binding = 0) readonly buffer Points { vec4 points[]; };
// Six vec4 per point (the CPU pre-pass's polynomial): (q, valid), (n, 0), (e1, 0), (e2, 0),
// (c0, c1, c2, c3), (c4, c5, l, 0).
layout(std430, binding = 1) readonly buffer Polys { vec4 polys[]; };

struct Quadratic {
    vec3 q, n, e1, e2;   // origin and frame of the reference plane H
    float c[6];          // g(u, v) = c0 + c1 u + c2 v + c3 u^2 + c4 u v + c5 v^2, in units of l
    float l;             // the fit's local kernel width
};

// g(u, v), in units of l
float quadratic_value(Quadratic g, float u, float v) {
    return g.c[0] + g.c[1] * u + g.c[2] * v + g.c[3] * u * u + g.c[4] * u * v + g.c[5] * v * v;
}

// Smallest t in [lo, hi] where o + t d meets the quadratic (polynomial.poly_ray); the
// caller puts o near the surface so the coefficients stay small in float32.
bool ray_quadratic(Quadratic g, vec3 o, vec3 d, float lo, float hi, out float t) {
    vec3 r = (o - g.q) / g.l;
    vec3 ds = d / g.l;
    float u0 = dot(r, g.e1), v0 = dot(r, g.e2), f0 = dot(r, g.n);
    float du = dot(ds, g.e1), dv = dot(ds, g.e2), df = dot(ds, g.n);
    float qa = g.c[3] * du * du + g.c[4] * du * dv + g.c[5] * dv * dv;
    float qb = g.c[1] * du + g.c[2] * dv + 2.0 * g.c[3] * u0 * du + g.c[4] * (u0 * dv + v0 * du)
             + 2.0 * g.c[5] * v0 * dv - df;
    float qc = quadratic_value(g, u0, v0) - f0;
    if (abs(qa) * (hi - lo) < 1e-6 * abs(qb)) {
        if (qb == 0.0) return false;
        t = -qc / qb;
        return t >= lo && t <= hi;
    }
    float disc = qb * qb - 4.0 * qa * qc;
    if (disc < 0.0) return false;
    float k = -0.5 * (qb + (qb >= 0.0 ? sqrt(disc) : -sqrt(disc)));  // stable pair of roots
    float t1 = k / qa;
    float t2 = k != 0.0 ? qc / k : t1;
    if (t1 > t2) { float s = t1; t1 = t2; t2 = s; }
    if (t1 >= lo && t1 <= hi) { t = t1; return true; }
    if (t2 >= lo && t2 <= hi) { t = t2; return true; }
    return false;
}

// Unit normal of the quadratic at (the foot point of) x: n - g_u e1 - g_v e2.
vec3 quadratic_normal(Quadratic g, vec3 x) {
    vec3 r = (x - g.q) / g.l;
    float u = dot(r, g.e1), v = dot(r, g.e2);
    float gu = g.c[1] + 2.0 * g.c[3] * u + g.c[4] * v;
    float gv = g.c[2] + g.c[4] * u + 2.0 * g.c[5] * v;
    return normalize(g.n - gu * g.e1 - gv * g.e2);
}

// The deterministic tangent basis of polynomial.tangent_frame.
void tangent_frame(vec3 n, out vec3 e1, out vec3 e2) {
    vec3 a = abs(n.x) < 0.6 ? vec3(1.0, 0.0, 0.0) : vec3(0.0, 1.0, 0.0);
    e1 = normalize(cross(a, n));
    e2 = cross(n, e1);
}

#if defined(PASS_INTERSECT) || defined(PASS_MEANS) || defined(PASS_SYSTEM)
#define DISC
#endif

// ---------------------------------------------------------------------------------------------
#ifdef VERTEX_SHADER
#ifdef DISC
// The point's rows (and in PASS_INTERSECT its polynomial's), read by each of its quad's vertices
// instead of each fragment: llvmpipe loads a storage buffer one lane at a time, and its
// fragment shaders read flat varyings as constants
flat out vec4 v_point[3];
#ifdef PASS_INTERSECT
flat out vec4 v_poly[6];
#endif
// Whether no pixel of the image-space box [lo, hi] (y down) has a failed candidate: at the
// mip level where the box spans at most 2 x 2 texels, their means are all zero. On a retry
// this drops the quads of all but the few points near such pixels before rasterization.
bool nothing_to_retry(vec2 lo, vec2 hi) {
    ivec2 last = ivec2(u_viewport) - 1;
    ivec2 a = clamp(ivec2(floor(vec2(lo.x - 0.5, u_viewport.y - hi.y - 0.5))), ivec2(0), last);
    ivec2 b = clamp(ivec2(floor(vec2(hi.x + 0.5, u_viewport.y - lo.y + 0.5))), ivec2(0), last);
    int level = 0;
    while (any(greaterThan((b >> level) - (a >> level), ivec2(1)))) level++;
    a >>= level;
    b >>= level;
    return texelFetch(u_failed, a, level).g + texelFetch(u_failed, ivec2(b.x, a.y), level).g
         + texelFetch(u_failed, ivec2(a.x, b.y), level).g + texelFetch(u_failed, b, level).g == 0.0;
}

// One instanced quad per point covering the exact screen bounding box of the sphere of
// radius R about p_i (the bounding sphere in PASS_INTERSECT, the kernel support otherwise):
// for an eye-space centre (a, z) the tangent lines give a/z ratios (a z -+ R sqrt(a^2 + z^2 - R^2)) / (z^2 - R^2).
void main() {
    int i = gl_InstanceID;
    v_point = vec4[3](points[3 * i], points[3 * i + 1], points[3 * i + 2]);
    vec4 ph = v_point[0];
#ifdef PASS_INTERSECT
    float radius = u_domain * v_point[1].w;
    v_poly = vec4[6](polys[6 * i], polys[6 * i + 1], polys[6 * i + 2], polys[6 * i + 3], polys[6 * i + 4],
                     polys[6 * i + 5]);
    if (v_poly[0].w == 0.0) { gl_Position = vec4(2.0, 2.0, 2.0, 1.0); return; }  // failed fit
#else
    float radius = SUPPORT * ph.w;
#endif
    vec3 c = (u_view * vec4(ph.xyz, 1.0)).xyz;
    vec2 corner = vec2(float(gl_VertexID & 1), float(gl_VertexID >> 1));
    vec2 lo, hi;  // image-space box, y down
    if (u_ortho > 0.0) {
        lo = vec2(u_intrinsics.z + (c.x - radius) * u_ortho, u_intrinsics.w - (c.y + radius) * u_ortho);
        hi = vec2(u_intrinsics.z + (c.x + radius) * u_ortho, u_intrinsics.w - (c.y - radius) * u_ortho);
    } else {
        float z = -c.z;
        if (z < -radius) { gl_Position = vec4(2.0, 2.0, 2.0, 1.0); return; }  // behind the camera
        if (z <= radius * 1.001) {  // the sphere contains the eye: the whole image
            lo = vec2(-1.0);
            hi = u_viewport + 1.0;
        } else {
            float k = z * z - radius * radius;
            vec2 s = radius * sqrt(c.xy * c.xy + k);
            vec2 rlo = (c.xy * z - s) / k, rhi = (c.xy * z + s) / k;
            lo = vec2(u_intrinsics.z + u_intrinsics.x * rlo.x, u_intrinsics.w - u_intrinsics.y * rhi.y);
            hi = vec2(u_intrinsics.z + u_intrinsics.x * rhi.x, u_intrinsics.w - u_intrinsics.y * rlo.y);
        }
    }
    if (u_retry && nothing_to_retry(lo, hi)) { gl_Position = vec4(2.0, 2.0, 2.0, 1.0); return; }
    // half a pixel of margin: rasterisation samples pixel centres
    gl_Position = image_to_clip(mix(lo - 0.5, hi + 0.5, corner));
#ifndef PASS_INTERSECT
    // The quad lies at the near end of the support: |p - r| < R needs z_p - R < t, so the depth
    // test against the hit depths (LEQUAL) drops the supports wholly behind the surface, e.g.
    // the far side of a closed object, before the fragment shader runs.
    float near_end = -c.z - 1.05 * radius;
    gl_Position.z = near_end <= u_depth_range.x ? -1.0 : clamp(2.0 * window_depth(vec3(0.0, 0.0, -near_end)) - 1.0, -1.0, 1.0);
#endif
}
#else
void main() {  // full-screen triangle
    vec2 p = vec2(float((gl_VertexID & 1) * 4 - 1), float((gl_VertexID >> 1) * 4 - 1));
    gl_Position = vec4(p, 0.0, 1.0);
}
#endif
#endif

// ---------------------------------------------------------------------------------------------
#ifdef FRAGMENT_SHADER
#ifdef DISC
flat in vec4 v_point[3];  // the point's rows: (p_i, h_i), (colour, s_i), (n_i, h_scale m_i)
#endif
#ifdef PASS_INTERSECT
flat in vec4 v_poly[6];  // its polynomial's
#endif
#if defined(PASS_MEANS) || defined(PASS_SYSTEM)
layout(early_fragment_tests) in;  // the depth test culls before shading (no depth is written)
#endif
// Ray of the fragment's pixel in local world coordinates; d.z in eye space is -1, so the
// ray parameter t is the eye depth.
void local_ray(out vec3 o, out vec3 d) {
    vec3 oe, de;
    pixel_ray(gl_FragCoord.xy, oe, de);
    o = (u_view_inv * vec4(oe, 1.0)).xyz;
    d = mat3(u_view_inv) * de;
}

uniform sampler2D u_state;      // r: current ray parameter t (>= MISS: no surface), g: last step / l,
                                // b: the current point's height over the last fit (FAR: none yet)
uniform sampler2D u_reference;  // the reference normal n_r of the pixel's next fit

#ifdef PASS_INTERSECT
Quadratic point_quadratic() {
    Quadratic g;
    g.q = v_poly[0].xyz;
    g.n = v_poly[1].xyz;
    g.e1 = v_poly[2].xyz;
    g.e2 = v_poly[3].xyz;
    vec4 a = v_poly[4], b = v_poly[5];
    g.c = float[6](a.x, a.y, a.z, a.w, b.x, b.y);
    g.l = b.z;
    return g;
}
#endif

// The current hit r of the fragment's pixel; false where the pixel has no surface.
bool current_hit(out vec3 r, out float t) {
    t = texelFetch(u_state, ivec2(gl_FragCoord.xy), 0).r;
    if (t >= MISS) return false;
    vec3 o, d;
    local_ray(o, d);
    r = o + t * d;
    return true;
}

#ifdef PASS_INTERSECT
layout(location = 0) out vec4 out_t;
layout(location = 1) out vec4 out_reference;
layout(location = 2) out vec4 out_first;  // t, kept for PASS_RETRY
layout(location = 3) out vec4 out_bracket;  // no iterate above or below the surface yet (PASS_SOLVE)
void main() {
    vec3 o, d;
    local_ray(o, d);
    float failed = u_retry ? texelFetch(u_failed, ivec2(gl_FragCoord.xy), 0).r : -FAR;
    if (failed >= MISS) discard;  // a later candidate: only where the earlier one failed
    vec3 oc = o - v_point[0].xyz;
    float radius = u_domain * v_point[1].w;
    float a = dot(d, d), b = dot(oc, d), c = dot(oc, oc) - radius * radius;
    float disc = b * b - a * c;
    if (disc < 0.0) discard;
    float t_in = max((-b - sqrt(disc)) / a, 0.0), t_out = (-b + sqrt(disc)) / a;
    if (t_out < 0.0) discard;
    float dt;
    // solved from the sphere entry so the quadratic's coefficients stay small
    if (!ray_quadratic(point_quadratic(), o + t_in * d, d, 0.0, t_out - t_in, dt)) discard;
    float t = t_in + dt;
    // beyond the failed candidate's sheet: its other samples meet the ray at nearly its t.
    // In units of the width the sample's density gives, h_scale m_i: a kernel widened across a
    // gap (widths.py) spans more than a thin part's thickness
    if (u_retry && t <= failed + RETRY_GAP * v_point[2].w) discard;
    out_t = vec4(t, 0.0, FAR, 0.0);
    out_first = out_t;
    out_bracket = vec4(-1.0, 0.0, -1.0, 0.0);
    out_reference = vec4(v_point[2].xyz, 0.0);
    gl_FragDepth = window_depth(vec3(0.0, 0.0, -t));  // nearest wins; the passes' depth test
}
#endif

#if defined(PASS_MEANS) || defined(PASS_SYSTEM)
// Weight of the disc's sample at r for the reference normal n_r (surface.gather): false
// outside its support. `facing` tells whether its normal lies on n_r's side.
bool kernel(vec3 r, out float w, out float d2, out bool facing) {
    vec4 ph = v_point[0];
    vec3 delta = ph.xyz - r;
    d2 = dot(delta, delta);
    if (d2 >= SUPPORT * SUPPORT * ph.w * ph.w) return false;
    vec3 normal = v_point[2].xyz;
    float cosine = dot(normal, texelFetch(u_reference, ivec2(gl_FragCoord.xy), 0).xyz);
    float residual = dot(normal, delta);  // r's distance from the sample's tangent plane
    facing = cosine > 0.0;
    w = exp(-(d2 + residual * residual * u_residual_weight) / (ph.w * ph.w) - 2.0 * (1.0 - cosine) * u_normal_weight);
    return true;
}
#endif

#ifdef PASS_MEANS
layout(location = 0) out vec4 out_sum;    // w x, w                   x = (p - r) / u_scale
layout(location = 1) out vec4 out_normal;  // w n_i, samples facing n_r
layout(location = 2) out vec4 out_inside;  // samples facing n_r that pass the domain test
layout(location = 3) out vec4 out_color;  // w rgb, w h / u_scale
void main() {
    vec3 r;
    float t, w, d2;
    bool facing;
    if (!current_hit(r, t) || !kernel(r, w, d2, facing)) discard;
    vec3 x = (v_point[0].xyz - r) / u_scale;
    float s = u_domain * v_point[1].w;
    out_sum = vec4(w * x, w);
    out_normal = vec4(w * v_point[2].xyz, facing ? 1.0 : 0.0);
    out_inside = vec4(facing && d2 < s * s ? 1.0 : 0.0, 0.0, 0.0, 0.0);
    out_color = vec4(w * v_point[1].rgb, w * v_point[0].w / u_scale);
}
#endif

#ifdef PASS_FRAME
uniform sampler2D u_sum;
uniform sampler2D u_normal_sum;
uniform sampler2D u_inside;
uniform sampler2D u_color;
layout(location = 0) out vec4 out_q;  // q = r + mean, 0
layout(location = 1) out vec4 out_n;  // n (facing n_r), l (0: the fit failed)

void main() {
    out_q = vec4(0.0);
    out_n = vec4(0.0);
    vec3 r;
    float t;
    ivec2 pix = ivec2(gl_FragCoord.xy);
    vec4 sum = texelFetch(u_sum, pix, 0), normal = texelFetch(u_normal_sum, pix, 0);
    // the fit's failure statuses: too few samples facing n_r, outside the domain, normals that
    // cancel out or turn away from n_r (surface.fit)
    if (!current_hit(r, t) || normal.w < u_min_neighbours || texelFetch(u_inside, pix, 0).x == 0.0) return;
    if (dot(normal.xyz, texelFetch(u_reference, pix, 0).xyz) <= 1e-9 * sum.w) return;
    vec3 m = sum.xyz / sum.w;
    vec3 n = normalize(normal.xyz);
    out_q = vec4(r + m * u_scale, 0.0);
    out_n = vec4(n, texelFetch(u_color, pix, 0).a / sum.w * u_scale);
}
#endif

#if defined(PASS_SYSTEM) || defined(PASS_SOLVE)
uniform sampler2D u_q;
uniform sampler2D u_n;
#endif

#ifdef PASS_SYSTEM
// The normal equations of the weighted quadratic fit need only the 15 moments w u^i v^j
// (i + j <= 4) and the 6 right-hand sides w f u^i v^j (i + j <= 2): 21 sums in 6 targets.
// A seventh holds the half-disc test's sums (edges.past_edge): weights a_i w_i with h_i
// replaced by l, the samples' offsets from r in units of l; a spare channel of the sixth
// counts the extent test's samples (edges.sample_beyond).
layout(location = 0) out vec4 out_m0;  // 1, u, v, uu
layout(location = 1) out vec4 out_m1;  // uv, vv, uuu, uuv
layout(location = 2) out vec4 out_m2;  // uvv, vvv, u4, u3v
layout(location = 3) out vec4 out_m3;  // u2v2, uv3, v4, f
layout(location = 4) out vec4 out_m4;  // fu, fv, fuu, fuv
layout(location = 5) out vec4 out_m5;  // fvv, samples of r's sheet beyond r
layout(location = 6) out vec4 out_m6;  // a w (p - r) / l, a w
void main() {
    vec3 r;
    float t, w, d2;
    bool facing;
    if (!current_hit(r, t) || !kernel(r, w, d2, facing)) discard;
    ivec2 pix = ivec2(gl_FragCoord.xy);
    vec4 n = texelFetch(u_n, pix, 0);
    if (n.w == 0.0) discard;
    vec3 e1, e2;
    tangent_frame(n.xyz, e1, e2);
    vec3 x = (v_point[0].xyz - texelFetch(u_q, pix, 0).xyz) / n.w;
    float u = dot(x, e1), v = dot(x, e2), f = dot(x, n.xyz);
    float uu = u * u, uv = u * v, vv = v * v;
    out_m0 = w * vec4(1.0, u, v, uu);
    out_m1 = w * vec4(uv, vv, uu * u, uu * v);
    out_m2 = w * vec4(u * vv, v * vv, uu * uu, uu * uv);
    out_m3 = w * vec4(uu * vv, uv * vv, vv * vv, f);
    out_m4 = w * f * vec4(u, v, uu, uv);
    // extent test: whether the sample lies out along `away`, the direction from the weighted
    // mean q to r within the plane, near the line from r that way (edges.sample_beyond); a
    // mean at r counts as a sample of r's sheet beyond r
    vec3 mean = texelFetch(u_q, pix, 0).xyz - r;
    vec3 away = dot(mean, n.xyz) * n.xyz - mean;
    float reach = length(away);
    vec3 offset = v_point[0].xyz - r;
    float forward = dot(offset, away) / max(reach, 1e-30), across = dot(offset, n.xyz);
    bool same_sheet = dot(v_point[2].xyz, n.xyz) > u_edge_cos;
    float sideways2 = dot(offset, offset) - forward * forward - across * across;
    bool alongside = sideways2 <= u_edge_lateral * u_edge_lateral * n.w * n.w;
    bool beyond = reach <= 1e-6 * n.w || (same_sheet && forward >= 0.0 && alongside);
    out_m5 = vec4(w * f * vv, beyond ? 1.0 : 0.0, 0.0, 0.0);
    float h = v_point[0].w;  // h_i^2: the area the sample stands for, up to a factor (edges.py)
    float wa = h * h * w * exp(d2 * (1.0 / (h * h) - 1.0 / (n.w * n.w)));
    out_m6 = wa * vec4((v_point[0].xyz - r) / n.w, 1.0);
}
#endif

#ifdef PASS_SOLVE
uniform sampler2D u_m0;
uniform sampler2D u_m1;
uniform sampler2D u_m2;
uniform sampler2D u_m3;
uniform sampler2D u_m4;
uniform sampler2D u_m5;
uniform sampler2D u_m6;
#ifdef SHADING_NORMAL
layout(location = 0) out vec4 out_normal;  // the shading fit's normal at r (the kept normal stays where it fails)
#else
uniform sampler2D u_color;  // w rgb of the means pass
uniform sampler2D u_weight; // (w x, w) of the means pass
// (t, height) of the last iterates above and below their fits (t < 0: none): raytrace.trace_ray's
// false position, which keeps a grazing ray from overshooting the surface further each step
uniform sampler2D u_bracket;
layout(location = 0) out vec4 out_state;      // new t (MISS if the fit failed), |step| / l, height
layout(location = 1) out vec4 out_reference;  // reference normal of the next fit
layout(location = 2) out vec4 out_normal;     // local world normal of the surface at the new point
layout(location = 3) out vec4 out_albedo;     // weighted mean colour of the neighbours
layout(location = 4) out vec4 out_bracket;
#endif

// The pixel's quadratic over its frame (q, n: n.w its local width l) from the moments of its
// normal equations; false where they are singular even regularised (degenerate).
bool solved_quadratic(ivec2 pix, vec4 q, vec4 n, out Quadratic g) {
    vec4 m0 = texelFetch(u_m0, pix, 0), m1 = texelFetch(u_m1, pix, 0), m2 = texelFetch(u_m2, pix, 0);
    vec4 m3 = texelFetch(u_m3, pix, 0), m4 = texelFetch(u_m4, pix, 0), m5 = texelFetch(u_m5, pix, 0);
    // moments by degree k and power of v j at index k (k + 1) / 2 + j
    double mom[15] = double[15](m0.x, m0.y, m0.z, m0.w, m1.x, m1.y, m1.z, m1.w, m2.x, m2.y, m2.z, m2.w,
                                m3.x, m3.y, m3.z);
    double b[6] = double[6](m3.w, m4.x, m4.y, m4.z, m4.w, m5.x);
    const ivec2 basis[6] = ivec2[6](ivec2(0, 0), ivec2(1, 0), ivec2(0, 1), ivec2(2, 0), ivec2(1, 1), ivec2(0, 2));
    double a[6][6];
    bool solved = false;
    // the least squares fit; where it is singular, the smoothest quadratic (surface.fit)
    for (int attempt = 0; attempt < 2 && !solved; attempt++) {
        double ridge = attempt == 0 ? 0.0 : double(u_ridge) * mom[0];
        for (int i = 0; i < 6; i++) {
            for (int j = 0; j < 6; j++) {
                ivec2 e = basis[i] + basis[j];
                int k = e.x + e.y;
                a[i][j] = mom[k * (k + 1) / 2 + e.y] + (i == j && i > 0 ? ridge : 0.0);
            }
        }
        // Cholesky (polynomial.solve_spd), in double: the moment matrix spans several decades
        solved = true;
        for (int j = 0; j < 6 && solved; j++) {
            double d = a[j][j];
            for (int k = 0; k < j; k++) d -= a[j][k] * a[j][k];
            if (d <= 1e-12 * a[0][0]) {
                solved = false;  // singular
                break;
            }
            d = sqrt(d);
            a[j][j] = d;
            for (int i = j + 1; i < 6; i++) {
                double s = a[i][j];
                for (int k = 0; k < j; k++) s -= a[i][k] * a[j][k];
                a[i][j] = s / d;
            }
        }
    }
    if (!solved) return false;
    for (int i = 0; i < 6; i++) {
        double s = b[i];
        for (int k = 0; k < i; k++) s -= a[i][k] * b[k];
        b[i] = s / a[i][i];
    }
    for (int i = 5; i >= 0; i--) {
        double s = b[i];
        for (int k = i + 1; k < 6; k++) s -= a[k][i] * b[k];
        b[i] = s / a[i][i];
    }
    g.q = q.xyz;
    g.n = n.xyz;
    g.l = n.w;
    tangent_frame(g.n, g.e1, g.e2);
    g.c = float[6](float(b[0]), float(b[1]), float(b[2]), float(b[3]), float(b[4]), float(b[5]));
    return true;
}

#ifdef SHADING_NORMAL
// The gradient of the fit under the shading weights at the pixel's hit (surface.py: shading normal)
void main() {
    vec3 r;
    float t;
    ivec2 pix = ivec2(gl_FragCoord.xy);
    vec4 q = texelFetch(u_q, pix, 0), n = texelFetch(u_n, pix, 0);
    Quadratic g;
    if (!current_hit(r, t) || n.w == 0.0 || !solved_quadratic(pix, q, n, g)) discard;
    out_normal = vec4(quadratic_normal(g, r), 1.0);
}
#else
void main() {
    out_state = vec4(FAR, 0.0, 0.0, 0.0);
    out_bracket = vec4(-1.0, 0.0, -1.0, 0.0);
    out_reference = vec4(0.0);
    out_normal = vec4(0.0);
    out_albedo = vec4(0.0);
    gl_FragDepth = 0.0;  // a miss: the next disc passes skip the pixel
    vec3 r;
    float t;
    ivec2 pix = ivec2(gl_FragCoord.xy);
    vec4 q = texelFetch(u_q, pix, 0), n = texelFetch(u_n, pix, 0);
    if (!current_hit(r, t) || n.w == 0.0) return;
    if (u_last) {  // the half-disc and extent tests where the projection converged: past the edge of its sheet?
        vec4 m6 = texelFetch(u_m6, pix, 0);
        vec3 mean = m6.xyz / m6.w;
        if (length(mean - dot(mean, n.xyz) * n.xyz) > u_boundary || texelFetch(u_m5, pix, 0).y == 0.0)
            return;
    }
    Quadratic g;
    if (!solved_quadratic(pix, q, n, g)) return;  // degenerate
    // r's height over its fit, kept on the side it lies (raytrace.trace_ray: the Illinois weight
    // halves an end kept twice)
    vec3 rl = (r - g.q) / g.l;
    float height = g.l * (dot(rl, g.n) - quadratic_value(g, dot(rl, g.e1), dot(rl, g.e2)));
    float last = texelFetch(u_state, pix, 0).b;
    vec4 bracket = texelFetch(u_bracket, pix, 0);  // t above, its height, t below, its height
    // converged (the CPU tracer stops there): the bracket, now stale, is left alone
    bool converged = abs(height) < u_tolerance * g.l;
    if (!converged) {
        if (height > 0.0) {
            if (last > 0.0) bracket.w *= 0.5;
            bracket.xy = vec2(t, height);
        } else {
            if (last <= 0.0) bracket.y *= 0.5;
            bracket.zw = vec2(t, height);
        }
    }
    bool stalled = abs(height) >= abs(last);
    // the ray meets the new quadratic near r (raytrace.trace_ray's window), solved from r
    vec3 o, d;
    local_ray(o, d);
    float dt, window = SUPPORT * g.l;
    bool met = ray_quadratic(g, r, d, max(-window, -t), window, dt);
    float next = met ? t + dt : -1.0;
    if (!converged && bracket.x >= 0.0 && bracket.z >= 0.0 && (!met || stalled)
            && !(min(bracket.x, bracket.z) < next && next < max(bracket.x, bracket.z)))
        next = bracket.x + (bracket.z - bracket.x) * bracket.y / (bracket.y - bracket.w);  // false position
    if (next < 0.0 || (u_last && abs(height) > LAST_HEIGHT * g.l)) return;
    dt = next - t;
    vec3 x = r + dt * d;
    vec4 weight = texelFetch(u_weight, pix, 0);
    out_state = vec4(next, length(dt * d) / g.l, height, 0.0);
    out_bracket = bracket;
    gl_FragDepth = window_depth(vec3(0.0, 0.0, -(t + dt)));
    out_normal = vec4(quadratic_normal(g, x), 1.0);
    out_reference = u_update_reference ? out_normal : texelFetch(u_reference, pix, 0);
    out_albedo = vec4(texelFetch(u_color, pix, 0).rgb / weight.w, 1.0);
}
#endif
#endif

#ifdef PASS_CULL
void main() {
    float t = texelFetch(u_state, ivec2(gl_FragCoord.xy), 0).r;
    gl_FragDepth = t < MISS ? window_depth(vec3(0.0, 0.0, -t)) : 0.0;
}
#endif

#if defined(PASS_KEEP) || defined(PASS_SHADE)
uniform sampler2D u_normal;
uniform sampler2D u_albedo;
#endif

#ifdef PASS_KEEP
layout(location = 0) out vec4 out_state;
layout(location = 1) out vec4 out_normal;
layout(location = 2) out vec4 out_albedo;
void main() {
    ivec2 pix = ivec2(gl_FragCoord.xy);
    out_state = texelFetch(u_state, pix, 0);
    if (out_state.r >= MISS) discard;  // what an earlier candidate found stays
    out_normal = texelFetch(u_normal, pix, 0);
    out_albedo = texelFetch(u_albedo, pix, 0);
}
#endif

#ifdef PASS_RETRY
uniform sampler2D u_first;
layout(location = 0) out vec4 out_failed;
void main() {
    ivec2 pix = ivec2(gl_FragCoord.xy);
    float first = texelFetch(u_first, pix, 0).r;
    // the target is cleared to (FAR, 0) (no retry); the fragments written are counted (gpu.py)
    if (first >= MISS || texelFetch(u_state, pix, 0).r < MISS) discard;
    out_failed = vec4(first, 1.0, 0.0, 0.0);
}
#endif

#ifdef PASS_SHADE
layout(location = 0) out vec4 out_shaded;
layout(location = 1) out vec4 out_eye_normal;
layout(location = 2) out vec4 out_depth;
void main() {
    ivec2 pix = ivec2(gl_FragCoord.xy);
    float t = texelFetch(u_state, pix, 0).r;
    out_shaded = vec4(0.0);
    out_eye_normal = vec4(0.0);
    out_depth = vec4(0.0);
    if (t >= MISS) return;
    vec3 oe, de;
    pixel_ray(gl_FragCoord.xy, oe, de);
    vec3 n = normalize(mat3(u_view) * texelFetch(u_normal, pix, 0).xyz);
    if (dot(n, -de) < 0.0) n = -n;  // two-sided: face the viewer
    vec3 albedo = blended_albedo(texelFetch(u_albedo, pix, 0).rgb);  // colour modes: colors.glsl
    out_shaded = vec4(shade(u_shading, albedo, n, t, u_depth_range.x, u_depth_range.y), 1.0);
    out_eye_normal = vec4(n, -1.0);  // categories: picked on the CPU (gpu.py)
    out_depth = vec4(t, 0.0, 0.0, 0.0);
}
#endif
#endif

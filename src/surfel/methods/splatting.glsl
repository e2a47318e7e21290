// GPU surface splatting (Botsch & Kobbelt 2003; Botsch, Hornung, Zwicker & Kobbelt 2005).
// One source, passes chosen by #define:
//   PASS_VISIBILITY  eye depth + z_t of every splat fragment, MIN-blended: the nearest surface
//   PASS_OCCLUSION   full-screen: that depth into the depth buffer (passes.glsl)
//   PASS_ATTRIBUTE   additive blending of weighted attributes of fragments within z_t of it;
//                    each splat drawn at the nearest depth it can have and depth-tested, so
//                    that fragments of splats hidden there never reach the fragment shader
//   PASS_CATEGORY    categorical colour modes: the packed (weight, palette index) of the same
//                    fragments, MAX-blended: the heaviest splat's category per pixel (colors.glsl)
//   PASS_NORMALIZE   full-screen: divide by the accumulated weight, then (deferred) shade
// With COMPUTE_SHADER, PASS_VISIBILITY and PASS_ATTRIBUTE are compute programs computing the
// same fragments, one invocation a splat (splat_setup, then its sprite's pixels), combined by
// atomics (passes.glsl); PASS_RESOLVE (passes.glsl) turns the visibility pass's minima into
// its target, and PASS_NORMALIZE with ACCUMULATOR_SUMS reads the attribute pass's sums.
// Variants: PER_SPLAT_SHADING (the 2003 Gouraud look: colours shaded per splat before
// blending) or deferred shading from blended normals (2005); EWA_FILTER (2005 screen-space
// filter approximation: the union of the object-space disk and a screen-space low-pass);
// CURVED_SPLATS (each splat is the curved surface its linear normal field describes: the
// ray meets that, so the splat ends at the surface's true contour, and reaches no farther
// than where its field has turned by MAX_RIM_TILT); NORMAL_FIELD (with
// CURVED_SPLATS: Botsch, Spernat & Kobbelt 2004, Phong splatting: the blended normal is the
// splat's linear normal field N(u, v) = n + u alpha u_j + v beta v_j, eq. 8, per fragment;
// `phong`'s, and `deferred`'s unless it blends one normal per splat as in its paper);
// CLIP_LINES (splats cut at sharp features by the clip lines of surfel.preprocess).
#include "common.glsl"
#include "lod.glsl"
#include "shading.glsl"
#include "passes.glsl"
#if defined(PASS_NORMALIZE) || defined(PASS_OCCLUSION) || defined(PASS_RESOLVE)
#define FULL_SCREEN  // passes.glsl's per-pixel passes, no splats
#endif

#define DEPTH_CLAMP 32.0  // splat radii: how far the plane's depth may stray from the centre's
#define BACK_SPLAT_WEIGHT (1.0 / 256.0)  // a back-facing splat's weight beside front-facing ones
#define BACK_SPLAT_BEHIND 1.0  // radii a back-facing splat's visibility depth lies further back
#define MAX_RIM_TILT 1.0  // a curved splat's field turns by at most this (tan 45 degrees) at its rim
#define CREASE_BLEND 0.5  // splat radii an attribute fragment reaches past a clip line, fading
#define CREASE_BLEND_DEPTH 2.0  // z_t's in front of the visible depth it may lie there
#define FULL_FOOTPRINT_AXIS 0.5  // pixels of semi-major axis below which a splat's footprint is whole
#define FAR_DEPTH 3.0e38  // the visibility target's clear value (gl/passes.py FAR): no surface

uniform float u_radius_scale;
uniform float u_depth_offset;    // z_t as a fraction of the splat radius
uniform float u_lowpass_radius;  // pixels
uniform int u_backface_culling;
uniform sampler2D u_kernel;      // Gaussian weight exp(-GAUSSIAN_SHARPNESS d^2) (splatting.py), indexed by d^2 in [0, 1]

// The splat's values that its fragments read: flat varyings from the vertex to the fragment
// stage, or in the compute variant (PASS_VISIBILITY with COMPUTE_SHADER: every splat's
// fragments visited by one invocation) plain globals, set per splat by splat_setup.
#ifndef FULL_SCREEN
#if defined(VERTEX_SHADER)
#define SPLAT_VARYING flat out
#elif defined(FRAGMENT_SHADER)
#define SPLAT_VARYING flat in
#else
#define SPLAT_VARYING
#endif
SPLAT_VARYING vec3 v_center;     // eye space
SPLAT_VARYING vec3 v_normal;     // eye space, facing the camera
SPLAT_VARYING vec3 v_u;          // axis_u / |axis_u|^2: dot(q - c, v_u) is the local coordinate u
SPLAT_VARYING vec3 v_v;
SPLAT_VARYING vec3 v_color;      // albedo (encoded, colors.glsl), or the per-splat shaded colour
SPLAT_VARYING float v_category;  // palette index of a categorical colour mode
SPLAT_VARYING vec2 v_center_px;  // projected centre in image pixels (for the low-pass)
SPLAT_VARYING float v_offset;    // z_t in eye units
SPLAT_VARYING float v_radius;    // largest semi-axis
SPLAT_VARYING float v_weight;    // EWA_FILTER: the resampling kernel's relative amplitude
SPLAT_VARYING float v_footprint; // EWA_FILTER: the share of the pixel-wide footprint off the disk
SPLAT_VARYING vec3 v_field_u;    // alpha u_j and beta v_j: the normal field's slopes (eye space)
SPLAT_VARYING vec3 v_field_v;
SPLAT_VARYING vec2 v_bend;       // CURVED_SPLATS: the surface's curvatures k_u, k_v along the axes
#ifdef CLIP_LINES
SPLAT_VARYING vec3 v_clip0;      // clip lines in local coordinates (sharp features)
SPLAT_VARYING vec3 v_clip1;
#endif
#endif

#if (defined(VERTEX_SHADER) || defined(COMPUTE_SHADER)) && !defined(FULL_SCREEN)
#include "splat_attributes.glsl"

vec2 to_pixels(vec3 eye) {
    if (u_ortho > 0.0) return vec2(u_intrinsics.z + u_ortho * eye.x, u_intrinsics.w - u_ortho * eye.y);
    return vec2(u_intrinsics.z + u_intrinsics.x * eye.x / -eye.z, u_intrinsics.w - u_intrinsics.y * eye.y / -eye.z);
}

#if defined(PASS_ATTRIBUTE) || defined(PASS_CATEGORY)
// The nearest eye depth that a fragment of the splat (centre c, unit normal n) in the image
// box [lo, hi] can have (splat_distance). Along the pixel rays the plane's depth t has an
// affine reciprocal (perspective) or is affine (orthographic) in the image coordinates, so
// where the plane faces every ray of the box from the same side its least value is at a
// corner; splat_distance clamps it to `extent` of the centre's depth. Curved splats
// (CURVED_SPLATS) leave the plane: only the clamp bounds them. Rounding in the fragment
// shader is covered by a relative margin of 1e-4.
float nearest_depth(vec3 c, vec3 n, vec2 lo, vec2 hi, float extent) {
    float nearest = -c.z - extent;
#ifndef CURVED_SPLATS
    float least = -c.z, side = 0.0;
    for (int i = 0; i < 4; ++i) {
        vec3 o, d;
        image_ray(vec2(i % 2 == 0 ? lo.x : hi.x, i < 2 ? lo.y : hi.y), o, d);
        float denom = dot(d, n);
        if (abs(denom) < 1e-3 * length(d) || denom * side < 0.0) return nearest;  // edge-on within the box
        side = denom;
        least = min(least, dot(c - o, n) / denom);
    }
    nearest = max(nearest, least);
#endif
    return nearest - 1e-4 * (abs(c.z) + extent);
}
#endif

#if defined(CURVED_SPLATS) && defined(CLIP_LINES)
// The clip line a u + b v <= c (unit (a, b)) of a splat in the coordinates of its axes divided
// by `reach`: the same line, unit again.
vec3 line_within_reach(vec3 line, vec2 reach) {
    vec2 ab = line.xy / reach;
    float norm = length(ab);
    return norm > 0.0 ? vec3(ab, line.z) / norm : line;
}
#endif

// What the vertex stage computes once per splat: the v_ values its fragments read, and its
// screen box [lo, hi] (image pixels, y down): with POINT_SPRITES the square sprite around it.
// False for a splat that draws nothing (level of detail, back-face culling, behind the near
// plane, cut away whole by a clip line).
bool splat_setup(out vec2 lo, out vec2 hi, out bool crosses_near) {
    lo = hi = vec2(0.0);
    crosses_near = false;
    vec3 c = (u_view * vec4(in_center, 1.0)).xyz;
    if (!lod_visible(c, in_lod.x, in_lod.y, in_lod.z)) return false;
    vec3 n = mat3(u_view) * in_normal;
    vec3 au = mat3(u_view) * in_axis_u * u_radius_scale;
    vec3 av = mat3(u_view) * in_axis_v * u_radius_scale;
    // the slopes are the fields' tilts at the fitted rim; the scaled splat's rim lies
    // u_radius_scale times as far, where they have turned as much more (splatting.py)
    vec2 field = in_field.xy * u_radius_scale;
#ifdef CURVED_SPLATS
    // A curved splat reaches no farther along each axis than where its surface has turned by
    // MAX_RIM_TILT, its slope there then at most that (splatting.py)
    vec2 bend = in_field.zw * u_radius_scale;  // shaped by the surface's field, shaded by the other (normal_field.py)
    vec2 reach = max(abs(bend) / MAX_RIM_TILT, 1.0);
    au /= reach.x;
    av /= reach.y;
    field /= reach;
    bend /= reach;
#endif
    if (!face_camera(c, n, au, av)) n = normalize(n);
    bool back = faces_away(c, n);
    if (back) n = -n;
    // the normal field turns with the normal when the splat is seen from its back
    v_field_u = (back ? -1.0 : 1.0) * field.x * normalize(au + 1e-30);
    v_field_v = (back ? -1.0 : 1.0) * field.y * normalize(av + 1e-30);
#ifdef CURVED_SPLATS
    v_bend = (back ? -1.0 : 1.0) * bend / max(vec2(length(au), length(av)), 1e-30);
#endif
    float near = u_depth_range.x;
    bool before_near = u_ortho == 0.0 && -c.z + length(au) + length(av) < near;  // wholly behind the camera's near plane
    bool culled = (back && u_backface_culling != 0) || before_near;
#ifdef CLIP_LINES
    culled = culled || in_clip0.z < -1.0 || in_clip1.z < -1.0;  // cut away whole (a crease point)
#endif
    if (culled) return false;
    // Conservative screen bounding box: the projected corners of the disk's bounding square
    // (exact for the rasterized disk, unlike eq. 6's sphere approximation). A splat crossing
    // the near plane gets the whole viewport, so it is never chopped.
    lo = vec2(1e30); hi = vec2(-1e30);
    for (int i = 0; i < 4; ++i) {
        vec3 p = c + (i % 2 == 0 ? -au : au) + (i < 2 ? -av : av);
        if (u_ortho == 0.0 && -p.z < near) { crosses_near = true; break; }
        vec2 s = to_pixels(p);
        lo = min(lo, s); hi = max(hi, s);
    }
    vec2 center_px = to_pixels(c);
#ifdef EWA_FILTER
    lo = min(lo, center_px - u_lowpass_radius); hi = max(hi, center_px + u_lowpass_radius);
    // EWA's normalization: the resampling kernel G_{S + r²I} has amplitude
    // sqrt(det S / det(S + r²I)) relative to the reconstruction kernel G_S, S = J V Jᵀ the
    // projected splat. Without it, edge-on and minified splats would weigh as much as a
    // full-size splat wherever the low-pass widens them.
    vec2 ju = to_pixels(c + au) - center_px, jv = to_pixels(c + av) - center_px;
    float r2 = u_lowpass_radius * u_lowpass_radius;
    float det_s = pow(ju.x * jv.y - ju.y * jv.x, 2.0);
    float trace_s = dot(ju, ju) + dot(jv, jv);
    v_weight = crosses_near ? 1.0 : sqrt(det_s / (det_s + r2 * trace_s + r2 * r2));
    // S's larger eigenvalue is the squared semi-major axis (footprint_edge)
    float major = sqrt(0.5 * (trace_s + sqrt(max(trace_s * trace_s - 4.0 * det_s, 0.0))));
    v_footprint = crosses_near ? 0.0 : clamp(FULL_FOOTPRINT_AXIS + 1.0 - major, 0.0, 1.0);
#else
    v_weight = 1.0;
    v_footprint = 1.0;
#endif
#ifndef PER_SPLAT_SHADING
    // Two-sided splats: one seen from its back is flipped to face the camera. At a closed
    // surface's silhouette the front's and the back's splats meet within z_t, and their
    // normals, both turned to the camera, would average to one facing it: a bright rim
    // (shading each splat first, `gaussian`, has no such average). So a back splat weighs
    // little where front splats cover the pixel, and fully, after the normalization, where
    // only back splats do (a sheet seen from behind).
    if (back) v_weight *= BACK_SPLAT_WEIGHT;
#endif
#ifdef POINT_SPRITES
    // One vertex per splat: a square sprite around the box, on a render target with a guard
    // band so that sprites centred outside the image still reach into it (OpenGL drops a
    // point whose centre is clipped). splatting.py picks quads when a splat could outgrow
    // the guard band or the largest point size, or cross the near plane.
    vec2 box_center = 0.5 * (lo + hi);
    float size = max(max(hi.x - lo.x, hi.y - lo.y), 1.0);  // covers every pixel centre in the box
    lo = box_center - 0.5 * size;  // the sprite's square
    hi = box_center + 0.5 * size;
#else
    if (crosses_near) { lo = vec2(0.0); hi = u_viewport; }
    lo = max(lo, vec2(-1.0)); hi = min(hi, u_viewport + 1.0);
#endif
    v_center = c;
    v_normal = n;
    v_u = au / max(dot(au, au), 1e-30);
    v_v = av / max(dot(av, av), 1e-30);
#ifdef PER_SPLAT_SHADING
    v_color = shade(u_shading, splat_albedo(in_color), n, -c.z, u_depth_range.x, u_depth_range.y);
#else
    v_color = in_color;
#endif
    v_category = category_index(in_color);
    v_center_px = center_px;
#if defined(CLIP_LINES) && defined(CURVED_SPLATS)
    v_clip0 = line_within_reach(in_clip0, reach);
    v_clip1 = line_within_reach(in_clip1, reach);
#elif defined(CLIP_LINES)
    v_clip0 = in_clip0;
    v_clip1 = in_clip1;
#endif
    v_radius = max(length(au), length(av));
    float offset = u_depth_offset;
#ifndef PER_SPLAT_SHADING
    if (back) offset += BACK_SPLAT_BEHIND;  // it hides no front splat that close (splatting.py)
#endif
    v_offset = layer_offset(offset * v_radius, c, n, in_thickness);
    return true;
}

#ifdef VERTEX_SHADER
void main() {
    vec2 lo, hi;
    bool crosses_near;
    if (!splat_setup(lo, hi, crosses_near)) {
        gl_Position = LOD_CULLED;  // outside the clip volume: no fragments
        return;
    }
#ifdef POINT_SPRITES
    gl_Position = image_to_clip(0.5 * (lo + hi));
    gl_PointSize = hi.x - lo.x;
#else
    const vec2 corners[4] = vec2[4](vec2(0.0, 0.0), vec2(1.0, 0.0), vec2(0.0, 1.0), vec2(1.0, 1.0));
    gl_Position = image_to_clip(mix(lo, hi, corners[gl_VertexID]));
#endif
#if defined(PASS_ATTRIBUTE) || defined(PASS_CATEGORY)
    // Occlusion culling: the splat is drawn at the nearest depth it can have, so that the
    // depth test (early, before the fragment shader) drops its fragments wherever even that
    // lies behind the visible surface. Half a pixel of margin covers the rasterizer's snapping.
    float nearest = crosses_near ? 0.0 : nearest_depth(v_center, v_normal, lo - 0.5, hi + 0.5, DEPTH_CLAMP * v_radius);
    gl_Position.z = 2.0 * depth_code(nearest) - 1.0;
#endif
}
#endif
#endif

#if (defined(FRAGMENT_SHADER) || defined(COMPUTE_SHADER)) && !defined(FULL_SCREEN)
#ifdef CURVED_SPLATS
// Curved splats: the surface whose normals are the splat's linear field is, to second order,
// the height field h(s_u, s_v) = -(k_u s_u² + k_v s_v²) / 2 over the splat plane, with s the
// metric tangent coordinates and k = alpha / |u_j|, beta / |v_j| the field's tilt per unit
// length (for a sphere of radius R, k = 1/R and h its cap). Step the ray parameter t from the
// plane's hit to the root of the ray-surface quadratic nearest it (expanded about the plane's
// hit, so that single precision keeps it). False where the ray misses the curved surface:
// it passes beyond the splat's contour, where the flat splat would stick out past the true
// outline of a curved surface, over whatever lies behind it.
float curved_quadratic(vec3 o, vec3 d, float denom, float t, out float qb, out float qc) {
    vec3 eu = normalize(v_u), ev = normalize(v_v), p0 = o + d * t - v_center;
    float ku = v_bend.x, kv = v_bend.y;
    float a0 = dot(p0, eu), a1 = dot(d, eu), b0 = dot(p0, ev), b1 = dot(d, ev);
    float qa = 0.5 * (ku * a1 * a1 + kv * b1 * b1);
    qb = denom + ku * a0 * a1 + kv * b0 * b1;
    qc = 0.5 * (ku * a0 * a0 + kv * b0 * b0);
    return qb * qb - 4.0 * qa * qc;
}

float curved_discriminant(vec2 frag) {
    vec3 o, d;
    pixel_ray(frag, o, d);
    float denom = dot(d, v_normal), qb, qc;
    return curved_quadratic(o, d, denom, dot(v_center - o, v_normal) / denom, qb, qc);
}

bool curved_splat_hit(vec3 o, vec3 d, float denom, inout float t) {
    float qb, qc;
    float disc = curved_quadratic(o, d, denom, t, qb, qc);
    if (disc < 0.0) return false;
    float h = -0.5 * (qb + (qb < 0.0 ? -1.0 : 1.0) * sqrt(disc));
    if (h != 0.0) t += qc / h;
    return true;
}
#endif

// Squared distance of the fragment to the splat centre in the kernel's unit domain (1e30
// where its ray misses the splat), and the eye depth of the splat seen there: the exact
// ray-plane intersection (perspective accurate), or with CURVED_SPLATS the ray's hit on the
// curved splat, located by its tangent coordinates. Low-pass fragments outside the disk keep
// the plane's depth too, so coplanar neighbours agree at grazing angles, where a pixel's
// footprint spans many splat radii in depth; only near-parallel rays are clamped to the
// splat's depth range. `clipped` is the clip_excess of the fragment: a splat cut at a sharp
// feature ends at its clip lines. `frag`: the fragment's window position (gl_FragCoord.xy).
float splat_distance(vec2 frag, out float eye_depth, out vec2 local_uv, out float clipped) {
    vec3 o, d;
    pixel_ray(frag, o, d);
    float denom = dot(d, v_normal);
    float rho2 = 1e30;
    float extent = DEPTH_CLAMP * v_radius;
    eye_depth = -v_center.z;
    local_uv = vec2(0.0);
    clipped = -1e30;  // no clip line near
    float t = dot(v_center - o, v_normal) / denom;
    bool hit = abs(denom) > 1e-12;
#ifdef CURVED_SPLATS
    hit = hit && curved_splat_hit(o, d, denom, t);
#endif
    if (hit) {
        vec3 q = o + d * t;
        vec3 local = q - v_center;
        float u = dot(local, v_u), v = dot(local, v_v);
        rho2 = u * u + v * v;
        local_uv = vec2(u, v);
#ifdef CLIP_LINES
        clipped = clip_excess(local_uv * u_radius_scale, v_clip0, v_clip1) / u_radius_scale;
#endif
        eye_depth = clamp(-q.z, -v_center.z - extent, -v_center.z + extent);
    }
    return rho2;
}

// The kernel distance of the resampling filter: with EWA_FILTER the union of the splat's
// reconstruction kernel (splat_rho2) and the screen-space low-pass, else the splat's own.
float filter_distance(vec2 frag, float splat_rho2) {
#ifdef EWA_FILTER
    vec2 delta = (image_coord(frag) - v_center_px) / u_lowpass_radius;
    return min(splat_rho2, dot(delta, delta));
#else
    return splat_rho2;
#endif
}

// The edge distance of a splat's pixel-wide footprint: a splat smaller than a pixel covers at
// least the pixel around its centre, since its own edge would leave every pixel of a dense
// cloud partly covered. Off the disk, where only the low-pass keeps a fragment, it covers the
// half-pixel around its centre, 1/2 - |x - m|: a pixel whose centre lies x beyond a dense
// cloud's last splats is covered 1/2 - x, as the outline covers it (1 - x widened every
// outline by half a pixel: 40.5 against 44.6 dB on 400k points of the bunny). That counts by
// the splat's share v_footprint: whole up to FULL_FOOTPRINT_AXIS pixels of semi-major axis,
// none from a pixel more, so that the resolved edge-on splats of an outline (noisy on a scan)
// do not widen it by the low-pass's reach. The CPU backend computes the same.
float footprint_edge(vec2 frag, float splat_rho2) {
    bool on_disk = splat_rho2 <= 1.0;
    float share = on_disk ? 1.0 : v_footprint;
    return share * ((on_disk ? 1.0 : 0.5) - length(image_coord(frag) - v_center_px)) - 0.5;
}

#if defined(PASS_ATTRIBUTE) || defined(PASS_CATEGORY)
// The attribute pass's fragment at window position `frag`, as its fragment shader, its
// compute program and the category pass take it: false where it is dropped (outside the
// filtered splat, CREASE_BLEND past a clip line, or off the visible surface); else its kernel
// weight w (fading past a clip line), eye depth z and normal n (the normal field's with
// NORMAL_FIELD). The kernel texture has one level, so textureLod (which compute programs
// need) reads what texture() would.
bool attribute_fragment(vec2 frag, out float w, out float z, out vec3 n) {
    float clipped;
    vec2 uv;
    float rho2 = filter_distance(frag, splat_distance(frag, z, uv, clipped));
    w = 0.0;
    n = v_normal;
    if (rho2 > 1.0 || clipped > CREASE_BLEND) return false;
    float visible = texelFetch(u_visibility, ivec2(frag), 0).r;
    if (z > visible) return false;  // behind the visible surface
    // past its clip line only where it meets the visible surface: across a crease (splatting.py)
    if (clipped > 0.0 && z < visible - CREASE_BLEND_DEPTH * v_offset) return false;
    w = v_weight * textureLod(u_kernel, vec2(rho2, 0.5), 0.0).r * min(1.0 - clipped / CREASE_BLEND, 1.0);
#ifdef NORMAL_FIELD
    n = field_normal(v_normal + uv.x * v_field_u + uv.y * v_field_v, v_center);
#endif
    return true;
}
#endif
#endif

#if defined(COMPUTE_SHADER) && !defined(FULL_SCREEN)
// The compute variants visit a splat's pixels in one invocation, without the rasterizer,
// whose cost per primitive (setting up a point sprite) is most of a splat pass's on a
// software renderer, and which GPUs too spend on splats of a few pixels (Schütz, Kerbl &
// Wimmer 2021, "Rendering point clouds with compute shaders and vertex order optimization").
layout(local_size_x = 64) in;
uniform int u_splat_count;

// This invocation's splat set up (splat_setup), and the window pixels (x, y: centre at +0.5)
// whose centres lie in its sprite, as the rasterizer's, inside the render target of `size`;
// false where there is no such splat or it draws nothing.
bool invocation_splat(ivec2 size, out ivec2 first, out ivec2 last) {
    first = ivec2(0);
    last = ivec2(-1);
    int i = int(gl_GlobalInvocationID.x);
    if (i >= u_splat_count) return false;
    load_splat_lod(i);
    if (!lod_visible((u_view * vec4(in_center, 1.0)).xyz, in_lod.x, in_lod.y, in_lod.z)) return false;
    load_splat(i);
    vec2 lo, hi;  // image pixels, y down
    bool crosses_near;
    if (!splat_setup(lo, hi, crosses_near)) return false;
    vec2 window_lo = vec2(lo.x + u_guard, u_viewport.y + u_guard - hi.y);
    vec2 window_hi = vec2(hi.x + u_guard, u_viewport.y + u_guard - lo.y);
    first = max(ivec2(ceil(window_lo - 0.5)), ivec2(0));
    last = min(ivec2(ceil(window_hi - 0.5)) - 1, size - 1);
    return true;
}

// The compute passes visit the pixels of [first, last] row by row in one loop, stepping with
// this: llvmpipe runs the invocations of a work group in lockstep, and two nested loops'
// bookkeeping cost the attribute pass about 8% more (bench, 1M splats).
ivec2 next_pixel(ivec2 texel, int first_x, int last_x) {
    return texel.x < last_x ? ivec2(texel.x + 1, texel.y) : ivec2(first_x, texel.y + 1);
}

int pixel_count(ivec2 first, ivec2 last) {
    return max(last.x - first.x + 1, 0) * max(last.y - first.y + 1, 0);
}
#endif

#if defined(PASS_VISIBILITY) && defined(COMPUTE_SHADER)
layout(r32ui, binding = 0) uniform uimage2D u_nearest;    // bits of the least depth + z_t
layout(r32ui, binding = 1) uniform uimage2D u_uncovered;  // bits of the least 1 - coverage

// The fragment shader's edge_distance, with rho's screen gradient analytic instead of a
// fragment quad's differences: grad rho = (u grad u + v grad v) / rho, d(u, v)/d(pixel) the
// splat plane's (for a curved splat too), or past a clip line that line's gradient. A curved
// splat also ends at its contour, where the discriminant of its quadratic falls to 0: the
// distance to that is the discriminant over its forward differences (where a fragment quad's
// neighbour misses the splat, the fragment shader's differences blow up to the same effect).
// The CPU backend (splatting_tiles.visibility_output) computes the same.
float analytic_edge_distance(vec2 frag, vec2 uv, float rho2, float clipped) {
    if (rho2 >= 1e30) return -1e30;  // the ray misses the splat
    vec3 o, d;
    pixel_ray(frag, o, d);
    // d(origin) and d(direction) per image pixel in x and y (image y runs down)
    vec3 dox = vec3(0.0), doy = vec3(0.0), ddx = vec3(0.0), ddy = vec3(0.0);
    if (u_ortho > 0.0) { dox.x = 1.0 / u_ortho; doy.y = -1.0 / u_ortho; }
    else { ddx.x = 1.0 / u_intrinsics.x; ddy.y = -1.0 / u_intrinsics.y; }
    float denom = dot(d, v_normal);
    float t = dot(v_center - o, v_normal) / denom;
    vec3 dqx = dox + ddx * t - d * ((dot(dox, v_normal) + t * dot(ddx, v_normal)) / denom);
    vec3 dqy = doy + ddy * t - d * ((dot(doy, v_normal) + t * dot(ddy, v_normal)) / denom);
    vec2 du = vec2(dot(dqx, v_u), dot(dqy, v_u)), dv = vec2(dot(dqx, v_v), dot(dqy, v_v));
    float rho = sqrt(rho2);
    float distance = 1.0 - rho;
    vec2 gradient = (uv.x * du + uv.y * dv) / max(rho, 1e-12);
#ifdef CLIP_LINES
    if (1.0 + clipped > rho) {
        vec2 scaled = uv * u_radius_scale;
        vec2 line = dot(v_clip0.xy, scaled) - v_clip0.z >= dot(v_clip1.xy, scaled) - v_clip1.z ? v_clip0.xy : v_clip1.xy;
        distance = -clipped;
        gradient = line.x * du + line.y * dv;
    }
#endif
    float edge = distance / max(length(gradient), 1e-6);
#ifdef CURVED_SPLATS
    float disc = curved_discriminant(frag);
    vec2 disc_gradient = vec2(curved_discriminant(frag + vec2(1.0, 0.0)), curved_discriminant(frag + vec2(0.0, 1.0))) - disc;
    edge = min(edge, disc / max(length(disc_gradient), 1e-30));
#endif
    return edge;
}

// The visibility pass as the fragment shader's PASS_VISIBILITY computes it, MIN-combined by
// atomics on the bits of non-negative floats (which order as the floats do); gl/passes.py
// resolves the two images into the visibility target.
void main() {
    ivec2 first, last;
    if (!invocation_splat(imageSize(u_nearest), first, last)) return;
    ivec2 texel = first;
    for (int k = pixel_count(first, last); k > 0; --k, texel = next_pixel(texel, first.x, last.x)) {
        vec2 frag = vec2(texel) + 0.5;
        float z, clipped;
        vec2 uv;
        float splat_rho2 = splat_distance(frag, z, uv, clipped);
        if (max(sqrt(filter_distance(frag, splat_rho2)), 1.0 + clipped) > 1.0) continue;
        float edge = max(analytic_edge_distance(frag, uv, splat_rho2, clipped), footprint_edge(frag, splat_rho2));
        uint depth = floatBitsToUint(splat_rho2 > 1.0 ? FAR_DEPTH : z + v_offset);
        uint uncovered = floatBitsToUint(1.0 - clamp(0.5 + edge, 0.0, 1.0));
        // most fragments lie behind one already there: a plain load spares their atomics
        if (depth < imageLoad(u_nearest, texel).x) imageAtomicMin(u_nearest, texel, depth);
        if (uncovered < imageLoad(u_uncovered, texel).x) imageAtomicMin(u_uncovered, texel, uncovered);
    }
}
#endif

#if defined(PASS_ATTRIBUTE) && defined(COMPUTE_SHADER)
// The attribute pass as the fragment shader's PASS_ATTRIBUTE computes it, summed by integer
// atomics in fixed point (passes.glsl ACCUMULATOR_SUMS: the sums' layout, scale and
// resolve), whose additions, unlike blended floats', give the same sums in any order.
void main() {
    ivec2 first, last;
    if (!invocation_splat(textureSize(u_visibility, 0), first, last)) return;
    ivec2 texel = first;
    for (int k = pixel_count(first, last); k > 0; --k, texel = next_pixel(texel, first.x, last.x)) {
        float w, z;
        vec3 n;
        if (attribute_fragment(vec2(texel) + 0.5, w, z, n)) accumulate(texel, w, v_color, n, z);
    }
}
#endif

#ifdef FRAGMENT_SHADER
#ifdef PASS_VISIBILITY
layout(location = 0) out vec4 out_depth;
void main() {
    float z, clipped;
    vec2 uv;
    float splat_rho2 = splat_distance(gl_FragCoord.xy, z, uv, clipped);
    // Coverage for anti-aliased silhouettes, to the edge of the splat itself (its rim or a
    // clip line), not of the low-pass, which filters but covers nothing, or to its footprint
    // (surrounded() in the normalization pass sees the pixels of a dense cloud whole).
    float edge = max(edge_distance(max(sqrt(splat_rho2), 1.0 + clipped)), footprint_edge(gl_FragCoord.xy, splat_rho2));
    float coverage = clamp(0.5 + edge, 0.0, 1.0);
    if (max(sqrt(filter_distance(gl_FragCoord.xy, splat_rho2)), 1.0 + clipped) > 1.0) discard;
    // A low-pass fragment off the disk filters but hides nothing: the edge-on splats of an
    // occluding contour would otherwise claim a pixel-wide band of the surface behind it,
    // drawn with their grazing normals.
    float depth = splat_rho2 > 1.0 ? FAR_DEPTH : z + v_offset;
    out_depth = vec4(depth, 1.0 - coverage, 0.0, 0.0);  // MIN blending: nearest, most covering
}
#endif

#ifdef PASS_ATTRIBUTE
layout(location = 0) out vec4 out_color;   // (w rgb, w)
layout(location = 1) out vec4 out_normal;  // (w n, w z)
void main() {
    float w, z;
    vec3 n;
    if (!attribute_fragment(gl_FragCoord.xy, w, z, n)) discard;
    out_color = vec4(w * v_color, w);
    out_normal = vec4(w * n, w * z);
}
#endif

#ifdef PASS_CATEGORY
layout(location = 0) out vec4 out_category;
void main() {  // the attribute pass's fragments and weights
    float w, z;
    vec3 n;
    if (!attribute_fragment(gl_FragCoord.xy, w, z, n)) discard;
    out_category = vec4(category_pack(w, v_category), -1.0, 0.0, 0.0);
}
#endif

#ifdef PASS_NORMALIZE
void main() {
    Accumulated a;
    if (!fetch_accumulated(int(u_guard), a)) return;
    if (surrounded(int(u_guard))) a.coverage = 1.0;
#ifdef PER_SPLAT_SHADING
    vec3 color = a.weighted_color / a.weight;  // shaded before blending
    if (a.category >= 0) color = shade(u_shading, table_entry(a.category), a.normal, a.depth, u_depth_range.x,
                                       u_depth_range.y);
#else
    vec3 color = shade(u_shading, pixel_albedo(a), a.normal, a.depth, u_depth_range.x, u_depth_range.y);  // deferred
#endif
    write_gbuffer(color, a);
}
#endif
#endif

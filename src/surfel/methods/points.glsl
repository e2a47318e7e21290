// Naive point rendering (survey Fig. 6, left): every point a screen-aligned disk of its
// projected radius (eq. 6), ordinary z-buffer, flat-shaded by its own normal, no filtering.
// Colour modes map each splat (colors.glsl splat_albedo); the G-buffer's normal.w carries a
// categorical mode's palette index (-1 otherwise) for the box filter.
#include "common.glsl"
#include "lod.glsl"
#include "shading.glsl"
uniform float u_radius_scale;

#ifdef VERTEX_SHADER
#include "splat_attributes.glsl"
flat out vec3 v_shaded;
flat out vec3 v_normal;
flat out float v_depth;
flat out float v_category;
void main() {
    vec4 eye = u_view * vec4(in_center, 1.0);
    if (!lod_visible(eye.xyz, in_lod.x, in_lod.y, in_lod.z)) { gl_Position = LOD_CULLED; return; }
    vec3 n = mat3(u_view) * in_normal;
    vec3 au = in_axis_u, av = in_axis_v;  // the sprite is screen-aligned: only their lengths matter
    if (!face_camera(eye.xyz, n, au, av)) n = normalize(n);
    if (faces_away(eye.xyz, n)) n = -n;
    float radius = u_radius_scale * max(length(au), length(av));
    // eq. 6: size_win = r * n / z_eye * h / (t - b), i.e. r * fy / z_eye pixels.
    float pixels = u_ortho > 0.0 ? radius * u_ortho : radius * u_intrinsics.y / max(-eye.z, 1e-9);
    gl_PointSize = max(2.0 * pixels, 1.0);
    v_shaded = shade(u_shading, splat_albedo(in_color), n, -eye.z, u_depth_range.x, u_depth_range.y);
    v_category = u_color_mode == COLOR_CATEGORICAL ? category_index(in_color) : -1.0;
    v_normal = n;
    v_depth = -eye.z;
    gl_Position = u_projection * eye;
}
#endif

#ifdef FRAGMENT_SHADER
flat in vec3 v_shaded;
flat in vec3 v_normal;
flat in float v_depth;
flat in float v_category;
layout(location = 0) out vec4 out_shaded;
layout(location = 1) out vec4 out_normal;
layout(location = 2) out vec4 out_depth;
void main() {
    vec2 p = 2.0 * gl_PointCoord - 1.0;
    if (dot(p, p) > 1.0) discard;
    out_shaded = vec4(v_shaded, 1.0);
    out_normal = vec4(v_normal, v_category);
    out_depth = vec4(v_depth, 0.0, 0.0, 0.0);
}
#endif

// Uniforms and helpers every surfel program shares.
#include "colors.glsl"
uniform mat4 u_view;        // world (relative to the cloud's local origin) to eye
uniform mat4 u_projection;  // eye to clip, reproducing the camera intrinsics
uniform vec2 u_viewport;    // image size in pixels (supersampled)
uniform float u_guard;      // guard band: the render target is the image plus this many pixels per side
uniform vec4 u_intrinsics;  // fx, fy, cx, cy in render-target pixels, image y down
uniform float u_ortho;      // 0: perspective; otherwise pixels per world unit of the orthographic view
uniform int u_shading;      // shading.glsl model id
uniform vec2 u_depth_range; // camera near and far, for depth shading

// Image coordinates (y down, origin at the image's top-left corner) of a fragment.
vec2 image_coord(vec2 frag_coord) {
    return vec2(frag_coord.x - u_guard, u_viewport.y + u_guard - frag_coord.y);
}

// Clip-space position (w = 1) of an image position, on the guard-banded render target.
vec4 image_to_clip(vec2 image) {
    vec2 target = u_viewport + 2.0 * u_guard;
    return vec4(2.0 * (image.x + u_guard) / target.x - 1.0, 1.0 - 2.0 * (image.y + u_guard) / target.y, 0.0, 1.0);
}

// Eye-space ray through a point of the image (pixels, y down): origin and (unnormalised)
// direction.
void image_ray(vec2 image, out vec3 origin, out vec3 direction) {
    if (u_ortho > 0.0) {
        origin = vec3((image.x - u_intrinsics.z) / u_ortho, (u_intrinsics.w - image.y) / u_ortho, 0.0);
        direction = vec3(0.0, 0.0, -1.0);
    } else {
        origin = vec3(0.0);
        direction = vec3((image.x - u_intrinsics.z) / u_intrinsics.x, (u_intrinsics.w - image.y) / u_intrinsics.y, -1.0);
    }
}

// Eye-space ray through the fragment's pixel centre.
void pixel_ray(vec2 frag_coord, out vec3 origin, out vec3 direction) {
    image_ray(image_coord(frag_coord), origin, direction);
}

// Window depth in [0, 1] of an eye-space point, for gl_FragDepth.
float window_depth(vec3 eye) {
    vec4 clip = u_projection * vec4(eye, 1.0);
    return 0.5 * clip.z / clip.w + 0.5;
}

// The visibility threshold z_t of a splat centred at eye-space c with unit normal n: `offset`
// (depth_offset x radius), capped where another surface lies within it by the thickness of the
// splat's layer (along its normal, preprocess/thickness.py; 0: no cap), as eye depth along
// the ray, which crosses the layer at |n . view|.
#define MIN_LAYER_COS 0.05  // a ray this close to the plane is left the uncapped offset's reach
float layer_offset(float offset, vec3 c, vec3 n, float thickness) {
    if (thickness <= 0.0) return offset;
    vec3 view = u_ortho > 0.0 ? vec3(0.0, 0.0, 1.0) : normalize(-c);
    return min(offset, thickness / max(abs(dot(n, view)), MIN_LAYER_COS));
}

// Whether the eye-space normal n at eye-space point p faces away from the camera (every
// method reports and shades the side that faces it).
bool faces_away(vec3 p, vec3 n) {
    return dot(n, u_ortho > 0.0 ? vec3(0.0, 0.0, 1.0) : -p) < 0.0;
}

// A splat packed with a zero normal has no orientation (surfel.preprocess.structure: a point on
// no surface, or without a tangent plane): it faces the camera. Its disk is turned perpendicular
// to the viewing ray through its centre c (eye space), its axes keeping their lengths, and its
// normal is the direction to the eye, so that it is shaded as a surface seen head-on. Returns
// whether it does; n (eye space, unnormalised) and the axes are changed only then.
bool face_camera(vec3 c, inout vec3 n, inout vec3 au, inout vec3 av) {
    if (dot(n, n) > 0.25) return false;
    n = u_ortho > 0.0 ? vec3(0.0, 0.0, 1.0) : normalize(-c);
    vec3 right = cross(vec3(0.0, 1.0, 0.0), n);  // zero only for a centre behind the camera
    right = dot(right, right) > 1e-12 ? normalize(right) : vec3(1.0, 0.0, 0.0);
    au = right * length(au);
    av = cross(n, right) * length(av);
    return true;
}

// The pixel centre's signed distance in pixels to a splat's edge, where its kernel distance
// rho is 1 (positive inside), from rho's screen-space gradient; 0.5 + it is the pixel's
// coverage, for anti-aliased silhouettes. Call before any discard, while the whole 2x2
// fragment quad is alive.
#ifdef FRAGMENT_SHADER
float edge_distance(float rho) {
    return (1.0 - rho) / max(length(vec2(dFdx(rho), dFdy(rho))), 1e-6);
}
#endif

// How far the local splat coordinates uv lie beyond the splat's clip lines (keep
// dot(line.xy, uv) <= line.z; sharp features, surfel.preprocess): > 0 means cut away.
float clip_excess(vec2 uv, vec3 line0, vec3 line1) {
    return max(dot(line0.xy, uv) - line0.z, dot(line1.xy, uv) - line1.z);
}

// A normal of Phong splatting's linear field (unnormalised) at a splat centred at eye point
// c, unit and turned no further than edge-on: extrapolated past the silhouette it would face
// away, and two-sided shading would light it as if it faced the viewer again.
vec3 field_normal(vec3 n, vec3 c) {
    vec3 to_eye = u_ortho > 0.0 ? vec3(0.0, 0.0, 1.0) : normalize(-c);
    return normalize(n - min(dot(n, to_eye), 0.0) * to_eye);
}

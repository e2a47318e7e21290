// Reference mesh rasterizer: smooth (per-pixel interpolated) normals, same shading as splats.
// Continuous colour modes interpolate the encoded vertex colours and map them per pixel
// (colors.glsl); categorical ones are picked on the CPU (mesh.py).
#include "common.glsl"
#include "shading.glsl"

#ifdef VERTEX_SHADER
in vec3 in_position;
in vec3 in_normal;
in vec3 in_color;
out vec3 v_eye;
out vec3 v_normal;
out vec3 v_color;
void main() {
    vec4 eye = u_view * vec4(in_position, 1.0);
    v_eye = eye.xyz;
    v_normal = mat3(u_view) * in_normal;
    v_color = in_color;
    gl_Position = u_projection * eye;
}
#endif

#ifdef FRAGMENT_SHADER
in vec3 v_eye;
in vec3 v_normal;
in vec3 v_color;
layout(location = 0) out vec4 out_shaded;
layout(location = 1) out vec4 out_normal;
layout(location = 2) out vec4 out_depth;
void main() {
    vec3 n = normalize(v_normal);
    if (faces_away(v_eye, n)) n = -n;  // report the side facing the camera
    out_shaded = vec4(shade(u_shading, blended_albedo(v_color), n, -v_eye.z, u_depth_range.x, u_depth_range.y), 1.0);
    out_normal = vec4(n, -1.0);
    out_depth = vec4(-v_eye.z, 0.0, 0.0, 0.0);
}
#endif

// The per-splat vertex attributes packed by gl/splats.py (one vertex, or one instance, a splat).
// A compute shader reads the same packed rows from a texture: load_splat_lod(i), then
// load_splat(i), set them.
#ifdef COMPUTE_SHADER
#define SPLAT_INPUT
#else
#define SPLAT_INPUT in
#endif
SPLAT_INPUT vec3 in_center;   // position relative to the cloud's local origin
SPLAT_INPUT vec3 in_normal;   // unit normal; zero: the splat faces the camera (common.glsl face_camera)
SPLAT_INPUT vec3 in_color;    // albedo
SPLAT_INPUT vec3 in_axis_u;   // tangent axes scaled to the ellipse's semi-axes
SPLAT_INPUT vec3 in_axis_v;
SPLAT_INPUT vec4 in_field;    // normal-field slopes: Phong splatting's (alpha, beta), then the curved surface's
SPLAT_INPUT vec3 in_lod;      // sequential point tree: e_g, the parent's e_g, the distance to the parent
SPLAT_INPUT vec3 in_clip0;    // clip lines at sharp features: keep dot(xy, (u, v)) <= z
SPLAT_INPUT vec3 in_clip1;
SPLAT_INPUT float in_thickness;  // its layer's thickness, z_t's cap (preprocess/thickness.py); 0: none

#ifdef COMPUTE_SHADER
// The packed rows of gl/splats.py `pack`, in the order above, as a compute program reads them:
// SPLAT_TEXELS RGBA32F texels a splat, SPLAT_ROW splats a texture row (gl/splats.py
// SplatBuffers.texels). llvmpipe loads a storage buffer's floats one lane at a time, each
// with its bounds test; a texel fetch loads a lane's four floats at once. The attribute pass of
// bench's frame (1M splats) stopped after its per-splat set-up: 103-120 ms from a storage
// buffer, 39 ms from the texture, of 200-240 ms for the whole pass before. GPUs read either
// through their caches.
uniform sampler2D u_splats;
vec4 splat_t0, splat_t4, splat_t5;  // the texels load_splat_lod reads, for load_splat

vec4 splat_texel(int i, int k) {
    return texelFetch(u_splats, ivec2((i % SPLAT_ROW) * SPLAT_TEXELS + k, i / SPLAT_ROW), 0);
}

// Splat i's centre and level-of-detail values: all that its level-of-detail test reads, so
// that the splats a cut leaves out cost no more fetches.
void load_splat_lod(int i) {
    splat_t0 = splat_texel(i, 0);
    splat_t4 = splat_texel(i, 4);
    splat_t5 = splat_texel(i, 5);
    in_center = splat_t0.xyz;
    in_lod = vec3(splat_t4.w, splat_t5.xy);
}

// The rest of splat i, after load_splat_lod.
void load_splat(int i) {
    vec4 t1 = splat_texel(i, 1), t2 = splat_texel(i, 2), t3 = splat_texel(i, 3);
    vec4 t6 = splat_texel(i, 6), t7 = splat_texel(i, 7);
    in_normal = vec3(splat_t0.w, t1.xy);
    in_color = vec3(t1.zw, t2.x);
    in_axis_u = t2.yzw;
    in_axis_v = t3.xyz;
    in_field = vec4(t3.w, splat_t4.xyz);
    in_clip0 = vec3(splat_t5.zw, t6.x);
    in_clip1 = t6.yzw;
    in_thickness = t7.x;
}
#endif

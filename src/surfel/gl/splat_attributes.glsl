// The per-splat vertex attributes packed by gl/splats.py (one vertex, or one instance, a splat).
// A compute shader reads the same packed buffer as a storage buffer: load_splat_lod(i), then
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
// The packed rows of gl/splats.py `pack`: SPLAT_FLOATS floats a splat, in the order above.
layout(std430, binding = 0) readonly buffer PackedSplats { float packed_splats[]; };

vec3 packed_vec3(int at) {
    return vec3(packed_splats[at], packed_splats[at + 1], packed_splats[at + 2]);
}

// Splat i's centre and level-of-detail values: all that its level-of-detail test reads, so
// that the splats a cut leaves out cost no more loads (llvmpipe's, one lane at a time, are
// most of a culled invocation's time).
void load_splat_lod(int i) {
    int at = i * SPLAT_FLOATS;
    in_center = packed_vec3(at);
    in_lod = packed_vec3(at + 19);
}

// The rest of splat i, after load_splat_lod.
void load_splat(int i) {
    int at = i * SPLAT_FLOATS;
    in_normal = packed_vec3(at + 3);
    in_color = packed_vec3(at + 6);
    in_axis_u = packed_vec3(at + 9);
    in_axis_v = packed_vec3(at + 12);
    in_field = vec4(packed_splats[at + 15], packed_splats[at + 16], packed_splats[at + 17], packed_splats[at + 18]);
    in_clip0 = packed_vec3(at + 22);
    in_clip1 = packed_vec3(at + 25);
    in_thickness = packed_splats[at + 28];
}
#endif

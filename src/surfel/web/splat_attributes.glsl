// The page's version of gl/splat_attributes.glsl (surfel.web): the same names, decoded from
// the quantized columns the page carries, so that methods/splatting.glsl runs unchanged in
// WebGL2. Positions: 16 bits per axis over the bounding box; normals: octahedral (Meyer et
// al. 2010, "On floating-point normal vectors"), 16 bits per component; ellipses: the two
// semi-axis lengths as half floats and the first axis's angle in the normal's tangent frame
// (Duff et al. 2017, "Building an orthonormal basis, revisited"), which surfel.web.pack
// computes from the same decoded normal. Colour modes: in_color is the encoded colour of
// surfel.colors (rgb, (t, valid, 0) or palette index / CODE_SCALE), which gl/colors.glsl
// decodes in splatting.glsl's passes exactly as on the desktop.
in vec3 a_position;  // [0, 1] over the bounding box
in vec2 a_normal;    // octahedral, [0, 1]
in vec2 a_radii;     // |axis_u|, |axis_v| in length units; |axis_u| negated: the splat faces the camera
in float a_angle;    // angle of axis_u in tangent_frame(normal), [0, 1) of a turn
in vec3 a_color;     // rgb albedo
in float a_value;    // the attribute the colour mode shows: 16-bit steps (normalized) or a palette index
in vec3 a_lod;       // e_g, the parent's e_g, the distance to the parent, in length units
in vec4 a_field;     // normal-field slopes: Phong splatting's (alpha, beta), then the curved surface's; 0 when absent
in vec3 a_clip0;     // clip lines in the local coordinates of axis_u, axis_v
in vec3 a_clip1;
in float a_thickness; // the layer's thickness, z_t's cap, in length units (0: none)

uniform vec3 u_box_lo;         // bounding box, relative to the cloud's local origin
uniform vec3 u_box_size;
uniform float u_length_unit;   // the box's longest side: radii and LOD lengths are stored in it
uniform int u_page_mode;       // PAGE_* below: what in_color encodes (gl/colors.glsl decodes it)
uniform vec2 u_value_range;    // the colour map's range (a_value's steps, or elevation)
uniform vec3 u_up;             // elevation axis

#define PAGE_RGB 0
#define PAGE_VALUE 1        // a continuous attribute, 16-bit steps over its range (the top step: not a number)
#define PAGE_ELEVATION 2    // dot(position, up)
#define PAGE_CODE 3         // a categorical attribute's palette index
#define VALUE_STEPS 65534.0

vec3 oct_decode(vec2 e) {
    e = 2.0 * e - 1.0;
    vec3 n = vec3(e, 1.0 - abs(e.x) - abs(e.y));
    float t = max(-n.z, 0.0);
    n.xy += vec2(n.x >= 0.0 ? -t : t, n.y >= 0.0 ? -t : t);
    return normalize(n);
}

void tangent_frame(vec3 n, out vec3 t1, out vec3 t2) {
    float s = n.z >= 0.0 ? 1.0 : -1.0;
    float a = -1.0 / (s + n.z);
    float b = n.x * n.y * a;
    t1 = vec3(1.0 + s * n.x * n.x * a, s * b, -s * n.x);
    t2 = vec3(b, s + n.y * n.y * a, -n.y);
}

vec3 splat_axis(bool second) {
    vec3 t1, t2;
    tangent_frame(oct_decode(a_normal), t1, t2);
    float phi = 6.283185307179586 * a_angle;
    vec3 u = cos(phi) * t1 + sin(phi) * t2;
    vec2 radii = abs(a_radii) * u_length_unit;
    return second ? radii.y * (cos(phi) * t2 - sin(phi) * t1) : radii.x * u;
}

// The colour the splat carries, encoded as surfel.colors.Coloring.encode does.
vec3 page_color() {
    if (u_page_mode == PAGE_RGB) return a_color;
    float steps = floor(a_value * 65535.0 + 0.5);
    if (u_page_mode == PAGE_CODE) return vec3(steps / CODE_SCALE, 0.0, 0.0);
    bool valid = u_page_mode == PAGE_ELEVATION || steps <= VALUE_STEPS;
    float value = u_page_mode == PAGE_ELEVATION ? dot(u_box_lo + a_position * u_box_size, u_up) : steps / VALUE_STEPS;
    float t = clamp((value - u_value_range.x) / max(u_value_range.y - u_value_range.x, 1e-30), 0.0, 1.0);
    return valid ? vec3(t, 1.0, 0.0) : vec3(0.0);
}

#define in_center (u_box_lo + a_position * u_box_size)
#define in_normal (a_radii.x < 0.0 ? vec3(0.0) : oct_decode(a_normal))  // zero: common.glsl face_camera
#define in_color page_color()
#define in_axis_u splat_axis(false)
#define in_axis_v splat_axis(true)
#define in_field a_field
#define in_lod (a_lod * u_length_unit)
#define in_clip0 a_clip0
#define in_clip1 a_clip1
#define in_thickness (a_thickness * u_length_unit)

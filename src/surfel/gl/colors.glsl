// Colour modes (surfel/colors.py states the equations and is the reference): what a splat's
// in_color holds and how a pixel's normalized colour becomes its albedo.
//   COLOR_RGB          in_color is the albedo
//   COLOR_CONTINUOUS   in_color = (t, valid, 0): the value's place in the colour map's range
//                      and whether it is a number; after blending, the map's LUT entry of
//                      t / valid, mixed towards u_neutral where values were not numbers
//   COLOR_CATEGORICAL  in_color.r = palette index / CODE_SCALE; never blended: a pass with
//                      MAX blending keeps the packed (weight level, index) of the heaviest
//                      splat per pixel (category_pack), whose palette entry the pixel shows
#define COLOR_RGB 0
#define COLOR_CONTINUOUS 1
#define COLOR_CATEGORICAL 2
#define CODE_SCALE 1048576.0
#define LUT_SIZE 256
#define PACKED_LEVELS 16777216.0
#define LOG2_WEIGHT_SPAN 128.0
#define TABLE_ROW 256

uniform int u_color_mode;
uniform sampler2D u_color_table;  // the colour map's LUT_SIZE entries, or the palette, TABLE_ROW a row
uniform vec3 u_neutral;           // the albedo of values that are not numbers
uniform float u_code_levels;      // palette indices per weight level in a packed category

vec3 table_entry(int index) {
    return texelFetch(u_color_table, ivec2(index % TABLE_ROW, index / TABLE_ROW), 0).rgb;
}

vec3 continuous_albedo(vec3 encoded) {
    float valid = min(encoded.g, 1.0);
    if (valid <= 0.0) return u_neutral;
    float t = clamp(encoded.r / valid, 0.0, 1.0);
    vec3 entry = table_entry(int(floor(t * float(LUT_SIZE - 1) + 0.5)));
    return valid >= 1.0 ? entry : mix(u_neutral, entry, valid);
}

float category_index(vec3 encoded) {
    return floor(encoded.r * CODE_SCALE + 0.5);
}

// The albedo of one splat: for the methods that shade each splat before blending.
vec3 splat_albedo(vec3 encoded) {
    if (u_color_mode == COLOR_CONTINUOUS) return continuous_albedo(encoded);
    if (u_color_mode == COLOR_CATEGORICAL) return table_entry(int(category_index(encoded)));
    return encoded;
}

// The albedo of a normalized (blended) colour; categorical pixels take category_unpack's entry.
vec3 blended_albedo(vec3 encoded) {
    return u_color_mode == COLOR_CONTINUOUS ? continuous_albedo(encoded) : encoded;
}

// (weight level, palette index) as one exactly representable float32; MAX blending keeps the
// heaviest splat's (ties: the larger index). colors.category_pack is the CPU twin.
float category_pack(float weight, float index) {
    float weight_levels = PACKED_LEVELS / u_code_levels;
    float level = floor((log2(max(weight, 1e-30)) + 0.5 * LOG2_WEIGHT_SPAN) / LOG2_WEIGHT_SPAN * weight_levels);
    return clamp(level, 0.0, weight_levels - 1.0) * u_code_levels + index;
}

// The palette index of a packed category, -1 where no splat packed one. In integers: packed
// values are exact integers up to 2^24, where adding 0.5 would round them to even.
int category_unpack(float value) {
    if (value < 0.0) return -1;
    return int(value) % int(u_code_levels);
}

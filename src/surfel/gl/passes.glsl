// The targets of three-pass splatting (gl/passes.py) and the normalization pass's plumbing:
// the full-screen triangle, reading the accumulated sums, writing the G-buffer.
uniform sampler2D u_visibility;   // (nearest depth + z_t, 1 - coverage) per pixel
uniform sampler2D u_accum_color;  // (sum w rgb, sum w)
uniform sampler2D u_accum_normal; // (sum w n, sum w z)
uniform sampler2D u_category;     // categorical colour modes: the packed category of the heaviest splat

// The depth buffer's code of an eye depth for the occlusion culling of the attribute pass:
// 1 - far / (z + far), rising with z, in floating point too (each operation rounds
// monotonically), 0 at the eye and 1 at the visibility pass's FAR.
float depth_code(float eye_depth) {
    return 1.0 - u_depth_range.y / (max(eye_depth, 0.0) + u_depth_range.y);
}

#if (defined(PASS_NORMALIZE) || defined(PASS_OCCLUSION)) && defined(VERTEX_SHADER)
#include "full_screen.glsl"
#endif

#if defined(PASS_OCCLUSION) && defined(FRAGMENT_SHADER)
// The visibility depth as the depth buffer of the attribute pass, whose splats are drawn at
// the nearest depth they can have (splatting.glsl nearest_depth) and depth-tested against it.
void main() {
    gl_FragDepth = depth_code(texelFetch(u_visibility, ivec2(gl_FragCoord.xy), 0).r);
}
#endif

#ifdef ACCUMULATOR_SUMS
// The compute attribute pass's sums (splatting.glsl): per pixel of the splat targets
// SUM_CHANNELS uints in fixed point, SUM_SCALE units to 1, signed values in two's complement:
// w r, w g, w b, w, w n (3), and w L, with L = log2(z / near) / log2(far / near) the eye depth
// z on a log scale of the camera's depth range (precise to about 3e-6 of z; the normalization
// pass turns the weighted mean of L back into the mean depth). A pixel stops accumulating past
// SUM_LIMIT of weight (a pile of hundreds of coincident splats), so that no sum overflows.
// With UNIFORM_COLOR (every splat's albedo code that value: a cloud without colours, not
// shaded per splat) the colour sums are the weight times it and are not accumulated: on
// llvmpipe the three atomics cost the attribute pass about 15% (bench, 1M splats).
#define SUM_CHANNELS 8
#define SUM_SCALE 4194304.0  // 2^22: weights to 2.4e-7
#define SUM_LIMIT 1073741824u  // 256 of weight, half the signed range of the depth and normal sums
layout(std430, binding = 1) buffer AccumulatorSums { uint accumulator_sums[]; };

int sum_base(ivec2 texel) {
    return (texel.y * int(u_viewport.x + 2.0 * u_guard) + texel.x) * SUM_CHANNELS;
}

float summed(int at) {
    return float(int(accumulator_sums[at])) / SUM_SCALE;
}

#ifdef COMPUTE_SHADER
uint fixed_point(float value) {
    return uint(int(round(value * SUM_SCALE)));
}

float log_depth(float z) {
    return clamp(log2(max(z, 1e-30) / u_depth_range.x) / log2(u_depth_range.y / u_depth_range.x), 0.0, 1.0);
}

void accumulate(ivec2 texel, float w, vec3 color, vec3 n, float z) {
    int at = sum_base(texel);
    uint weight = fixed_point(w);
    if (weight == 0u) return;
    // Admit the splat only while the weight sum stays under SUM_LIMIT, by compare-and-swap:
    // adding first and taking back past the limit lets thousands of threads of a GPU add at
    // once on a pile, and the sum wraps through 2^32 before they take back.
    uint seen = accumulator_sums[at + 3];
    while (true) {
        if (seen > SUM_LIMIT) return;
        uint before = atomicCompSwap(accumulator_sums[at + 3], seen, seen + weight);
        if (before == seen) break;
        seen = before;
    }
#ifndef UNIFORM_COLOR
    atomicAdd(accumulator_sums[at], fixed_point(w * color.r));
    atomicAdd(accumulator_sums[at + 1], fixed_point(w * color.g));
    atomicAdd(accumulator_sums[at + 2], fixed_point(w * color.b));
#endif
    atomicAdd(accumulator_sums[at + 4], fixed_point(w * n.x));
    atomicAdd(accumulator_sums[at + 5], fixed_point(w * n.y));
    atomicAdd(accumulator_sums[at + 6], fixed_point(w * n.z));
    atomicAdd(accumulator_sums[at + 7], fixed_point(w * log_depth(z)));
}
#endif
#endif

#if defined(PASS_RESOLVE) && defined(COMPUTE_SHADER)
// The compute visibility pass's images (splatting.glsl) into the visibility target.
layout(local_size_x = 16, local_size_y = 16) in;
layout(r32ui, binding = 0) uniform readonly uimage2D u_nearest;
layout(r32ui, binding = 1) uniform readonly uimage2D u_uncovered;
layout(rg32f, binding = 2) uniform writeonly image2D u_visibility_out;
void main() {
    ivec2 texel = ivec2(gl_GlobalInvocationID.xy);
    if (any(greaterThanEqual(texel, imageSize(u_nearest)))) return;
    imageStore(u_visibility_out, texel, vec4(uintBitsToFloat(imageLoad(u_nearest, texel).x),
                                             uintBitsToFloat(imageLoad(u_uncovered, texel).x), 0.0, 0.0));
}
#endif

#if defined(PASS_NORMALIZE) && defined(FRAGMENT_SHADER)
layout(location = 0) out vec4 out_shaded;
layout(location = 1) out vec4 out_normal;
layout(location = 2) out vec4 out_depth;

struct Accumulated {
    vec3 weighted_color;  // sum w rgb
    float weight;         // sum w
    vec3 normal;          // normalized sum w n
    float depth;          // sum w z / sum w
    float coverage;       // of the pixel, from the visibility pass
    int category;         // palette index of a categorical colour mode, else -1
};

// The attribute pass's (sum w rgb, sum w) and (sum w n, sum w z) at a texel of the splat
// targets whose sum w is `weight` > 0 (`accumulated_weight`): the accumulators', or with
// ACCUMULATOR_SUMS the compute pass's fixed-point sums.
void accumulated_sums(ivec2 texel, float weight, out vec4 color, out vec4 normal) {
#ifdef ACCUMULATOR_SUMS
    int at = sum_base(texel);
#ifdef UNIFORM_COLOR
    color = vec4(vec3(weight * UNIFORM_COLOR), weight);
#else
    color = vec4(summed(at), summed(at + 1), summed(at + 2), weight);
#endif
    float depth = u_depth_range.x * exp2(summed(at + 7) / weight * log2(u_depth_range.y / u_depth_range.x));
    normal = vec4(summed(at + 4), summed(at + 5), summed(at + 6), weight * depth);
#else
    color = texelFetch(u_accum_color, texel, 0);
    normal = texelFetch(u_accum_normal, texel, 0);
#endif
}

float accumulated_weight(ivec2 texel) {
#ifdef ACCUMULATOR_SUMS
    return summed(sum_base(texel) + 3);
#else
    return texelFetch(u_accum_color, texel, 0).a;
#endif
}

// The sums at this fragment's pixel (`guard`: the splat targets' margin); false where no
// splat contributed, after writing the empty G-buffer there. The weight is read first: most
// pixels of a view are empty, and on llvmpipe each storage-buffer read the others would take
// costs (bench: 5% of a `deferred` frame).
bool fetch_accumulated(int guard, out Accumulated a) {
    ivec2 texel = ivec2(gl_FragCoord.xy) + ivec2(guard);
    float weight = accumulated_weight(texel);
    if (weight <= 0.0) {
        out_shaded = vec4(0.0); out_normal = vec4(0.0); out_depth = vec4(0.0);
        return false;
    }
    vec4 color, normal;
    accumulated_sums(texel, weight, color, normal);
    a.weighted_color = color.rgb;
    a.weight = color.a;
    a.normal = length(normal.xyz) > 0.0 ? normalize(normal.xyz) : vec3(0.0, 0.0, 1.0);
    a.depth = normal.a / color.a;
    a.coverage = 1.0 - texelFetch(u_visibility, texel, 0).g;
    a.category = u_color_mode == COLOR_CATEGORICAL ? category_unpack(texelFetch(u_category, texel, 0).r) : -1;
    return true;
}

// Whether splats reach this fragment's pixel's four neighbours, each covering a neighbour's
// centre (coverage at least a half): a pixel inside the surface, whole, whatever the
// visibility pass's coverage of its single most covering splat (which a dense cloud's
// sub-pixel splats leave below one everywhere). Not the low-pass's weight: that reaches a
// pixel beyond an outline, which its neighbours would then make whole.
bool surrounded(int guard) {
    ivec2 texel = ivec2(gl_FragCoord.xy) + ivec2(guard), last = textureSize(u_accum_color, 0) - 1;
    const ivec2 steps[4] = ivec2[4](ivec2(1, 0), ivec2(-1, 0), ivec2(0, 1), ivec2(0, -1));
    for (int i = 0; i < 4; ++i)
        if (texelFetch(u_visibility, clamp(texel + steps[i], ivec2(0), last), 0).g > 0.5) return false;
    return true;
}

// The pixel's albedo: the winning category's palette entry, or the normalized colour decoded.
vec3 pixel_albedo(Accumulated a) {
    return a.category >= 0 ? table_entry(a.category) : blended_albedo(a.weighted_color / a.weight);
}

// The G-buffer: shaded colour and coverage, the normal and the category's palette index
// (read back for the box filter, which never mixes categories), the depth.
void write_gbuffer(vec3 shaded, Accumulated a) {
    out_shaded = vec4(shaded, a.coverage);
    out_normal = vec4(a.normal, float(a.category));
    out_depth = vec4(a.depth, 0.0, 0.0, 0.0);
}
#endif

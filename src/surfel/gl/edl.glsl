// Eye-dome lighting, the GLSL twin of surfel/edl.py (the reference, where the equations are
// stated): the term of one texel of a depth texture (eye distance along the viewing axis in
// .r, <= 0 where nothing is drawn), radius in texels, summed over SCALES radii r, 2r, 4r,
// opposite neighbours compared in pairs with their mean.
// Valid GLSL 4.30 and GLSL ES 3.00: the page and the tests compile it.
#define EDL_DIRECTIONS 8
#define EDL_SCALES 3
#define EDL_RESPONSE_SCALE 300.0

float edl_log_depth(sampler2D depth, ivec2 texel) {
    ivec2 size = textureSize(depth, 0);
    if (texel.x < 0 || texel.y < 0 || texel.x >= size.x || texel.y >= size.y) return -1e30;
    float z = texelFetch(depth, texel, 0).r;
    return z > 0.0 && z < 1e30 ? log2(z) : -1e30;  // -1e30: empty
}

// Bilinear log depth at a continuous texel position over the covered texels; false where none is.
bool edl_sample(sampler2D depth, vec2 position, out float value) {
    vec2 base = floor(position), f = position - base;
    float total = 0.0, weight = 0.0;
    for (int i = 0; i < 4; ++i) {
        ivec2 offset = ivec2(i % 2, i / 2);
        float v = edl_log_depth(depth, ivec2(base) + offset);
        if (v <= -1e29) continue;
        float w = (offset.x == 1 ? f.x : 1.0 - f.x) * (offset.y == 1 ? f.y : 1.0 - f.y);
        total += w * v;
        weight += w;
    }
    value = weight > 1e-6 ? total / weight : 0.0;
    return weight > 1e-6;
}

float edl_term(sampler2D depth, ivec2 texel, float radius, float strength) {
    float here = edl_log_depth(depth, texel);
    if (here <= -1e29) return 1.0;
    float total = 0.0;
    for (int k = 0; k < EDL_SCALES; ++k) {
        float r = radius * exp2(float(k)), response = 0.0;
        for (int i = 0; i < EDL_DIRECTIONS / 2; ++i) {  // opposite neighbours in pairs
            float angle = 6.283185307179586 * float(i) / float(EDL_DIRECTIONS);
            vec2 offset = r * vec2(cos(angle), sin(angle));
            float one, other;
            bool has_one = edl_sample(depth, vec2(texel) + offset, one);
            bool has_other = edl_sample(depth, vec2(texel) - offset, other);
            if (has_one && has_other) response += max(0.0, 2.0 * here - one - other);
            else if (has_one) response += max(0.0, here - one);
            else if (has_other) response += max(0.0, here - other);
        }
        total += response / float(EDL_DIRECTIONS) / exp2(0.5 * float(k));
    }
    return exp(-EDL_RESPONSE_SCALE * strength * total);
}

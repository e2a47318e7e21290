// One round of surfel/pinholes.py in the page (its docstring states the rule and the fill):
// G-buffer in, G-buffer out (shaded rgb + coverage, eye normal + palette index, eye depth),
// each sample that at least 7 of its 8 neighbours u_step samples away hide from behind
// filled from those in front. The page runs two rounds at a step of one sample between its
// normalization pass and display.glsl, and when it supersamples two more at a step of a
// pixel, as RenderResult.from_samples does before eye-dome lighting. Neighbours in the order
// of the Python module's rows (top row first: +y in the texture), so ties fall alike.

#ifdef VERTEX_SHADER
#include "full_screen.glsl"
#endif

#ifdef FRAGMENT_SHADER
#define MIN_FRONT 7
#define RELATIVE_TOLERANCE 1e-5
#define EMPTY 3.0e38           // the depth of an uncovered sample: behind everything
uniform sampler2D u_shaded;    // shaded rgb, coverage
uniform sampler2D u_gnormal;   // eye normal, palette index
uniform sampler2D u_gdepth;    // eye depth (0: empty)
uniform int u_categorical;
uniform int u_step;            // samples between a sample and its neighbours
layout(location = 0) out vec4 out_shaded;
layout(location = 1) out vec4 out_normal;
layout(location = 2) out vec4 out_depth;

const ivec2 NEIGHBOURS[8] = ivec2[8](ivec2(-1, 1), ivec2(0, 1), ivec2(1, 1), ivec2(-1, 0), ivec2(1, 0),
                                     ivec2(-1, -1), ivec2(0, -1), ivec2(1, -1));

float sample_depth(ivec2 texel) {
    return texelFetch(u_shaded, texel, 0).a > 0.0 ? texelFetch(u_gdepth, texel, 0).r : EMPTY;
}

bool is_pinhole(ivec2 texel, float z) {
    ivec2 last = textureSize(u_gdepth, 0) - u_step;
    if (any(lessThan(texel, ivec2(u_step))) || any(greaterThan(texel, last))) return false;
    int behind = 0;
    float near = EMPTY, far = -EMPTY;
    for (int i = 0; i < 8; ++i) {
        float q = sample_depth(texel + u_step * NEIGHBOURS[i]);
        if (q < z) {
            near = min(near, q);
            far = max(far, q);
        } else if (++behind > 8 - MIN_FRONT) {
            return false;
        }
    }
    return z - far > (far - near) + RELATIVE_TOLERANCE * abs(far);
}

void main() {
    ivec2 texel = ivec2(gl_FragCoord.xy);
    out_shaded = texelFetch(u_shaded, texel, 0);
    out_normal = texelFetch(u_gnormal, texel, 0);
    out_depth = texelFetch(u_gdepth, texel, 0);
    float z = sample_depth(texel);
    if (!is_pinhole(texel, z)) return;
    if (u_categorical != 0) {  // a copy of the first front neighbour showing the most common category
        int best_votes = 0;
        for (int i = 0; i < 8; ++i) {
            ivec2 q = texel + u_step * NEIGHBOURS[i];
            if (sample_depth(q) >= z) continue;
            float category = texelFetch(u_gnormal, q, 0).w;
            int votes = 0;
            for (int j = 0; j < 8; ++j) {
                ivec2 r = texel + u_step * NEIGHBOURS[j];
                if (sample_depth(r) < z && texelFetch(u_gnormal, r, 0).w == category) ++votes;
            }
            if (votes > best_votes) {
                best_votes = votes;
                out_shaded = texelFetch(u_shaded, q, 0);
                out_normal = texelFetch(u_gnormal, q, 0);
                out_depth = texelFetch(u_gdepth, q, 0);
            }
        }
        return;
    }
    vec4 shaded = vec4(0.0);
    vec3 normal = vec3(0.0);
    float depth = 0.0, count = 0.0;
    for (int i = 0; i < 8; ++i) {
        ivec2 q = texel + u_step * NEIGHBOURS[i];
        if (sample_depth(q) >= z) continue;
        shaded += texelFetch(u_shaded, q, 0);
        normal += texelFetch(u_gnormal, q, 0).xyz;
        depth += texelFetch(u_gdepth, q, 0).r;
        count += 1.0;
    }
    out_shaded = shaded / count;
    out_normal = vec4(length(normal) > 0.0 ? normalize(normal) : normal, out_normal.w);
    out_depth = vec4(depth / count, out_depth.yzw);
}
#endif

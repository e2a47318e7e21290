// Categorical colour modes (classification, return number, any integer code) are never
// blended (CONVENTIONS.md, "Colour"): a fourth pass of the page, after the visibility pass,
// keeps per pixel the code of the splat that weighs most there among those the attribute
// pass would blend. MIN blending of (255 (1 - w), quantized) * 65536 + code: the heaviest
// splat wins, ties go to the smaller code; both fit a float32 mantissa exactly.
// The vertex stage and the fragment tests are methods/splatting.glsl's, with the colour mode
// COLOR_CODE carrying the code in v_color.r.
#include "splatting.glsl"

#ifdef FRAGMENT_SHADER
layout(location = 0) out vec4 out_category;
void main() {
    float z, clipped;
    vec2 uv;
    float rho2 = filter_distance(splat_distance(z, uv, clipped));
    if (rho2 > 1.0 || clipped > 0.0) discard;
    if (z > texelFetch(u_visibility, ivec2(gl_FragCoord.xy), 0).r) discard;  // as the attribute pass
    float w = v_weight * texture(u_kernel, vec2(rho2, 0.5)).r;
    out_category = vec4(floor(255.0 * (1.0 - clamp(w, 0.0, 1.0))) * 65536.0 + v_color.r, 0.0, 0.0, 0.0);
}
#endif

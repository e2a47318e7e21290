// The page's last pass: the G-buffer of methods/splatting.glsl's normalization pass (shaded
// rgb + coverage, eye normal, eye depth) to the canvas, as surfel.result composites it:
// supersamples box-filtered with colour premultiplied by coverage, then over the background.
// Categorical colour modes take each sample's colour from the category pass and shade it
// here (shading.glsl, the same model). Eye-dome lighting (Boucheny 2009, "Interactive
// scientific visualization of large datasets", as Potree does it) multiplies the unlit
// colour by exp(-300 s R), R = (1/8) sum over 8 neighbours at radius r pixels of
// max(0, log2 z - log2 z_neighbour), so that a sample behind its neighbours darkens and flat,
// unoccluded areas keep their albedo.
#include "shading.glsl"

#ifdef VERTEX_SHADER
void main() {  // full-screen triangle
    vec2 p = vec2((gl_VertexID << 1) & 2, gl_VertexID & 2);
    gl_Position = vec4(2.0 * p - 1.0, 0.0, 1.0);
}
#endif

#ifdef FRAGMENT_SHADER
uniform sampler2D u_shaded;    // shaded rgb, coverage
uniform sampler2D u_gnormal;   // eye normal
uniform sampler2D u_gdepth;    // eye depth
uniform sampler2D u_category;  // the category pass's packed (weight, code), guard-banded
uniform sampler2D u_palette;   // 256 x 1: a category's colour
uniform int u_shading;
uniform vec2 u_depth_range;
uniform int u_categorical;
uniform int u_edl;
uniform float u_edl_strength;
uniform float u_edl_radius;    // pixels of the G-buffer
uniform int u_supersample;     // G-buffer samples per pixel side
uniform int u_downsample;      // or pixels per G-buffer sample (a coarse frame while the camera moves)
uniform int u_guard;
uniform vec3 u_background;
layout(location = 0) out vec4 out_color;

float log_depth(ivec2 texel) {
    ivec2 last = textureSize(u_gdepth, 0) - 1;
    ivec2 t = clamp(texel, ivec2(0), last);
    if (texelFetch(u_shaded, t, 0).a <= 0.0) return 1e30;  // no surface: occludes nothing
    return log2(max(texelFetch(u_gdepth, t, 0).r, 1e-30));
}

float edl(ivec2 texel) {
    float here = log2(max(texelFetch(u_gdepth, texel, 0).r, 1e-30));
    float r = u_edl_radius, sum = 0.0;
    for (int i = 0; i < 8; ++i) {
        float a = 0.7853981633974483 * float(i);
        ivec2 offset = ivec2(floor(r * vec2(cos(a), sin(a)) + 0.5));
        sum += max(0.0, here - log_depth(texel + offset));
    }
    return exp(-300.0 * u_edl_strength * sum / 8.0);
}

void main() {
    ivec2 pixel = ivec2(gl_FragCoord.xy);
    vec3 premultiplied = vec3(0.0);
    float alpha = 0.0;
    for (int sy = 0; sy < u_supersample; ++sy) {
        for (int sx = 0; sx < u_supersample; ++sx) {
            ivec2 texel = pixel / u_downsample * u_supersample + ivec2(sx, sy);
            vec4 shaded = texelFetch(u_shaded, texel, 0);
            float coverage = clamp(shaded.a, 0.0, 1.0);
            if (coverage <= 0.0) continue;
            vec3 color = shaded.rgb;
            if (u_categorical != 0) {
                float packed = texelFetch(u_category, texel + ivec2(u_guard), 0).r;
                float code = packed - 65536.0 * floor(packed / 65536.0);
                vec3 albedo = texelFetch(u_palette, ivec2(int(code) % 256, 0), 0).rgb;
                color = shade(u_shading, albedo, texelFetch(u_gnormal, texel, 0).xyz,
                              texelFetch(u_gdepth, texel, 0).r, u_depth_range.x, u_depth_range.y);
            }
            if (u_edl != 0) color *= edl(texel);
            premultiplied += coverage * color;
            alpha += coverage;
        }
    }
    float n = float(u_supersample * u_supersample);
    alpha /= n;
    out_color = vec4(clamp(premultiplied / n + (1.0 - alpha) * u_background, 0.0, 1.0), 1.0);
}
#endif

// The page's last pass: the G-buffer of methods/splatting.glsl's normalization pass (shaded
// rgb + coverage, eye normal + the palette index of a categorical colour mode, eye depth) to
// the canvas, as surfel.result.RenderResult.from_samples makes the output: eye-dome lighting
// (gl/edl.glsl, the twin of surfel.edl) multiplies each sample's unlit colour, then the
// supersamples are box-filtered with colour premultiplied by coverage (in a categorical mode
// a pixel takes the category covering most of it, never a mix), then composited over the
// background.
#include "edl.glsl"

#ifdef VERTEX_SHADER
#include "full_screen.glsl"
#endif

#ifdef FRAGMENT_SHADER
#define MAX_SAMPLES 16         // the page supersamples at most 4 x 4 (request.PAGE_MAX_SUPERSAMPLE)
uniform sampler2D u_shaded;    // shaded rgb, coverage
uniform sampler2D u_gnormal;   // eye normal, palette index
uniform sampler2D u_gdepth;    // eye depth (0: empty)
uniform int u_categorical;
uniform int u_edl;
uniform float u_edl_strength;
uniform float u_edl_radius;    // texels of the G-buffer
uniform int u_supersample;     // G-buffer samples per pixel side
uniform int u_downsample;      // or pixels per G-buffer sample (a coarse frame while the camera moves)
uniform vec3 u_background;
layout(location = 0) out vec4 out_color;

void main() {
    ivec2 pixel = ivec2(gl_FragCoord.xy);
    vec3 colors[MAX_SAMPLES];
    float coverages[MAX_SAMPLES], categories[MAX_SAMPLES];
    int count = u_supersample * u_supersample;
    float alpha = 0.0;
    for (int i = 0; i < count; ++i) {
        ivec2 texel = pixel / u_downsample * u_supersample + ivec2(i % u_supersample, i / u_supersample);
        vec4 shaded = texelFetch(u_shaded, texel, 0);
        coverages[i] = clamp(shaded.a, 0.0, 1.0);
        categories[i] = texelFetch(u_gnormal, texel, 0).w;
        colors[i] = shaded.rgb;
        if (u_edl != 0 && coverages[i] > 0.0) colors[i] *= edl_term(u_gdepth, texel, u_edl_radius, u_edl_strength);
        alpha += coverages[i];
    }
    float best = -1.0, best_weight = 0.0;
    for (int i = 0; i < count && u_categorical != 0; ++i) {  // the category covering most of the pixel
        if (coverages[i] <= 0.0) continue;
        float weight = 0.0;
        for (int j = 0; j < count; ++j) weight += categories[j] == categories[i] ? coverages[j] : 0.0;
        if (weight > best_weight) { best = categories[i]; best_weight = weight; }
    }
    vec3 sum = vec3(0.0);
    float total = 0.0;
    for (int i = 0; i < count; ++i) {
        if (coverages[i] <= 0.0 || (best >= 0.0 && categories[i] != best)) continue;
        sum += coverages[i] * colors[i];
        total += coverages[i];
    }
    alpha /= float(count);
    vec3 premultiplied = total > 0.0 ? sum / total * alpha : vec3(0.0);
    out_color = vec4(clamp(premultiplied + (1.0 - alpha) * u_background, 0.0, 1.0), 1.0);
}
#endif

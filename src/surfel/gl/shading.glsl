// Shading models of docs/conventions.md; shading.py holds the same formulas for the CPU paths.
// Eye space: the camera looks down -z, so the head-light direction v is (0, 0, 1).
// SHADING_* ids match shading.MODELS.
#define SHADING_LAMBERT 0
#define SHADING_PHONG 1
#define SHADING_NONE 2
#define SHADING_NORMALS 3
#define SHADING_DEPTH 4

vec3 shade(int model, vec3 albedo, vec3 n, float eye_depth, float near_depth, float far_depth) {
    if (model == SHADING_LAMBERT) {
        return albedo * (0.2 + 0.8 * abs(n.z));
    }
    if (model == SHADING_PHONG) {
        vec3 nf = n.z < 0.0 ? -n : n;  // two-sided
        const vec3 light = normalize(vec3(-0.4, 0.6, 0.8));  // key light from the upper left
        const vec3 halfway = normalize(light + vec3(0.0, 0.0, 1.0));
        float diffuse = 0.25 + 0.75 * max(dot(nf, light), 0.0);
        float specular = 0.3 * pow(max(dot(nf, halfway), 0.0), 40.0);
        return albedo * diffuse + vec3(specular);
    }
    if (model == SHADING_NORMALS) {
        return 0.5 * n + 0.5;
    }
    if (model == SHADING_DEPTH) {
        float t = clamp((eye_depth - near_depth) / max(far_depth - near_depth, 1e-12), 0.0, 1.0);
        return vec3(1.0 - t);
    }
    return albedo;  // SHADING_NONE
}

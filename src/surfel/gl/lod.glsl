// Sequential point trees (Dachsbacher, Vogelgsang & Stamminger 2003; survey section 2.2.2):
// the vertex-stage [r_min, r_max] test. The CPU draws only a prefix of the node list
// (surfel.lod.sequential.prefix_count); each vertex then decides whether its node is part
// of the current cut through the point tree, and a splat shader culls it otherwise.
//
// Per-vertex inputs (extras of a LOD cloud, see surfel/lod/format.py):
//   emin    = e_g of the node        (r_min = emin * k)
//   emax    = e_g of its parent      (r_max = emax * k; the root holds FLT_MAX)
//   dparent = |c - c_parent|, world units
// Per-frame uniform u_lod_k = k: fy / eps (perspective) or pixels-per-unit / eps
// (orthographic), in OUTPUT-image pixels (not the supersampled target's), <= 0: LOD off.
//
// Perspective: r = eye distance of the node's centre; drawn iff
//     emin * k <= r   and   r - dparent < emax * k
// (the second test bounds the parent's own distance from below, so that whenever the
// parent is refined its children are drawn: no holes; see surfel/lod/sequential.py).
// Orthographic: the projected error e_g * ppu does not depend on r; drawn iff
//     emin * k <= 1   and   1 < emax * k          (r = 1, dparent = 0)
// Both comparisons are half-open, so along a root-to-leaf path with one common r exactly
// one node passes.
uniform float u_lod_k;

bool lod_selected(float view_distance, float emin, float emax, float dparent, float k) {
    return emin * k <= view_distance && view_distance - dparent < emax * k;
}

// The test for a vertex at eye-space position `eye` under the common.glsl camera:
// switches on u_ortho (> 0: orthographic) and passes everything when u_lod_k <= 0.
bool lod_visible(vec3 eye, float emin, float emax, float dparent) {
    if (u_lod_k <= 0.0) return true;
    if (u_ortho > 0.0) return lod_selected(1.0, emin, emax, 0.0, u_lod_k);
    return lod_selected(length(eye), emin, emax, dparent, u_lod_k);
}

// Clip position that no primitive survives: outside the clip volume (w > 0, |x| > w), so a
// culled point, sprite or quad generates no fragments.
const vec4 LOD_CULLED = vec4(2.0, 2.0, 2.0, 1.0);

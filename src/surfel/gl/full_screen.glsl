// The vertex shader of a full-screen pass: one triangle over the whole viewport, made from
// gl_VertexID alone (no vertex buffer). Valid GLSL 4.30 and GLSL ES 3.00: the page uses it too.
void main() {
    vec2 p = vec2((gl_VertexID << 1) & 2, gl_VertexID & 2);
    gl_Position = vec4(2.0 * p - 1.0, 0.0, 1.0);
}

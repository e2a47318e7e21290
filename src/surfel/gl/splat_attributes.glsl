// The per-splat vertex attributes packed by gl/splats.py (one vertex, or one instance, a splat).
in vec3 in_center;   // position relative to the cloud's local origin
in vec3 in_normal;   // unit normal; zero: the splat faces the camera (common.glsl face_camera)
in vec3 in_color;    // albedo
in vec3 in_axis_u;   // tangent axes scaled to the ellipse's semi-axes
in vec3 in_axis_v;
in vec2 in_field;    // Phong splatting's normal-field slopes (alpha, beta)
in vec3 in_lod;      // sequential point tree: e_g, the parent's e_g, the distance to the parent
in vec3 in_clip0;    // clip lines at sharp features: keep dot(xy, (u, v)) <= z
in vec3 in_clip1;
in float in_thickness;  // its layer's thickness, z_t's cap (preprocess/thickness.py); 0: none

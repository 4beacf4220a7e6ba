#version 300 es
precision highp float;
in vec3 v_world;
uniform vec3 u_lightPosition;
out vec4 outColor;
void main() { outColor = vec4(length(v_world - u_lightPosition), 0.0, 0.0, 1.0); }

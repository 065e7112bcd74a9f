/* VolumeEVM's GPU method, vertex stage: the full-screen quad. Each fragment gets its normalized
   device coordinates (ndc), from which the fragment stage makes the pixel's ray. Interface and
   uniforms are declared by blender/gpu_draw.py (GPUShaderCreateInfo). */
void main()
{
  ndc = pos;
  gl_Position = vec4(pos, 0.0, 1.0);
}

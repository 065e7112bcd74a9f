/* A coarser frame stretched over the bound framebuffer: each pixel shows the ray of the coarse
   pixel it lies in (no filtering: the frame as drawn). */
void main()
{
  out_color = texelFetch(image, ivec2((ndc * 0.5 + 0.5) * vec2(textureSize(image, 0))), 0);
}

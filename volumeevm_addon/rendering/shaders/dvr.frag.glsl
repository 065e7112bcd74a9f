/* VolumeEVM's GPU method, fragment stage: the pixel's ray through the region's 3D texture,
   classified by the transfer-function table, composited front to back (over, X-ray or MIP)
   with the same optical model, opacity correction and visibility rule as the CPU renderers
   (volumeevm_addon/rendering/), leaping over empty blocks. struct VolumeParams and the mode
   and depth constants come from GPU_UNIFORMS_GLSL (_gpu_inputs.py); DISPLAY_SHAPER is filled
   in by blender/gpu_draw.py (the display table's shaper exponent). */

/* The line p = o + t d against the box [lo, hi]: narrows [t0, t1], false when it misses. */
bool clip_box(vec3 o, vec3 d, vec3 lo, vec3 hi, inout float t0, inout float t1)
{
  for (int i = 0; i < 3; i++) {
    if (d[i] == 0.0) {
      if (o[i] < lo[i] || o[i] > hi[i]) {
        return false;
      }
    }
    else {
      float a = (lo[i] - o[i]) / d[i];
      float b = (hi[i] - o[i]) / d[i];
      t0 = max(t0, min(a, b));
      t1 = min(t1, max(a, b));
    }
  }
  return t1 > t0;
}

/* Where the line leaves the box [lo, hi] (it is inside it). */
float box_exit(vec3 o, vec3 d, vec3 lo, vec3 hi)
{
  float t = 3.0e38;
  for (int i = 0; i < 3; i++) {
    if (d[i] != 0.0) {
      t = min(t, max((lo[i] - o[i]) / d[i], (hi[i] - o[i]) / d[i]));
    }
  }
  return t;
}

/* Whether the cell of voxel c (clamped to the grid) is in the region. */
bool in_region(ivec3 c)
{
  return texelFetch(region, clamp(c, ivec3(0), ivec3(params.grid.xyz) - 1), 0).g > 0.5;
}

/* The part of a ray from pf to pb (index space): the fraction of it lying in region cells, and
 * where (as a fraction) its first piece in a region cell starts, -1 for none. The part is cut
 * where it crosses cell boundaries (index m + 0.5; at most one per axis for steps up to a
 * voxel), so the region's surface is placed exactly, as the CPU ray caster places it. */
vec2 coverage(vec3 pf, vec3 pb)
{
  ivec3 cf = ivec3(floor(pf + 0.5));
  ivec3 cb = ivec3(floor(pb + 0.5));
  if (cf == cb) {
    return in_region(cf) ? vec2(1.0, 0.0) : vec2(0.0, -1.0);
  }
  vec3 span = pb - pf;
  vec3 cut = vec3(1.0);
  for (int i = 0; i < 3; i++) {
    if (cf[i] != cb[i]) {
      cut[i] = clamp((float(max(cf[i], cb[i])) - 0.5 - pf[i]) / span[i], 0.0, 1.0);
    }
  }
  /* sorted: e1 <= e2 <= e3 */
  float e1 = min(cut.x, min(cut.y, cut.z));
  float e3 = max(cut.x, max(cut.y, cut.z));
  float e2 = cut.x + cut.y + cut.z - e1 - e3;
  float edges[5] = float[5](0.0, e1, e2, e3, 1.0);
  float part = 0.0;
  float start = -1.0;
  for (int j = 0; j < 4; j++) {
    float piece = edges[j + 1] - edges[j];
    if (piece > 0.0 && in_region(ivec3(floor(pf + (0.5 * (edges[j] + edges[j + 1])) * span + 0.5))))
    {
      part += piece;
      if (start < 0.0) {
        start = edges[j];
      }
    }
  }
  return vec2(part, start);
}

/* The straight colour rgb lit by the headlight for the index-space gradient g, the unit world
 * direction towards the light (the ray's) and the fade: _shading.headlight's formula. */
vec3 headlight(vec3 rgb, vec3 g, vec3 towards)
{
  vec3 n = (params.normal * vec4(g, 0.0)).xyz;
  float norm = length(n);
  float cosine = norm > 0.0 ? abs(dot(n, towards)) / norm : 0.0;
  float m = length(g);
  float t = m <= params.fade.x ? 0.0 : (m >= params.fade.y ? 1.0 :
                                        smoothstep(params.fade.x, params.fade.y, m));
  float shininess = params.shading.w;
  float highlight = cosine > 0.0 ? pow(cosine, shininess) : (shininess == 0.0 ? 1.0 : 0.0);
  float lit = params.shading.x + params.shading.y * (1.0 - t + t * cosine);
  return min(rgb * lit + t * params.shading.z * highlight, vec3(1.0));
}

/* Straight colour and opacity per unit length of a density (linear in the table; a label of a
 * categorical function: its own row). */
vec4 classify(float value)
{
  float x = clamp((value - params.table.x) * params.table.y, 0.0, params.table.z - 1.0);
  if (params.labels.x > 0.5) {
    return texelFetch(tf_table, int(x + 0.5), 0);
  }
  return texture(tf_table, (x + 0.5) / params.table.z);
}

/* (density, weight) at p: trilinear over the region's voxels, or (categorical function) the
 * nearest voxel's label and whether that voxel is in the region. */
vec2 sample_region(vec3 p, ivec3 cell, vec3 to_texture)
{
  if (params.labels.x > 0.5) {
    return texelFetch(region, cell, 0).rg;
  }
  return texture(region, (p + 0.5) * to_texture).rg;
}

void main()
{
  out_color = vec4(0.0);
  out_depth = BACKGROUND_DEPTH;
  /* The pixel's ray in index space: o + t d at axial depth clip.z + t. */
  vec3 o = (params.ray_origin * vec4(ndc, 1.0, 0.0)).xyz;
  vec3 d = (params.ray_direction * vec4(ndc, 1.0, 0.0)).xyz;
  float t0 = params.clip.x;
  float t1 = params.clip.y;
  if (params.image.z > 0.5) {
    ivec2 pixel = ivec2((ndc * 0.5 + 0.5) * params.image.xy);
    t1 = min(t1, texelFetch(depth_in, pixel, 0).r - params.clip.z);
  }
  vec3 n = params.grid.xyz;
  if (!clip_box(o, d, vec3(-0.5), n - 0.5, t0, t1)) {
    return;
  }
  /* Equal parts no longer than the step, sampled at their midpoints. */
  float length_mm = (t1 - t0) * length(d * params.spacing.xyz);
  float parts = max(ceil(length_mm / params.spacing.w * (1.0 - 1e-6)), 1.0);
  float dt = (t1 - t0) / parts;
  float part_mm = length_mm / parts;
  float units = part_mm / params.table.w;
  int mode = int(params.compositing.x);
  bool skip = params.blocks.w > 0.5;
  int block = int(params.grid.w);
  ivec3 last_cell = ivec3(n) - 1;
  vec3 to_texture = 1.0 / n;
  bool shaded = params.fade.z > 0.5;
  vec3 towards = normalize((params.to_world * vec4(d, 0.0)).xyz);

  vec4 acc = vec4(0.0);
  float tau = 0.0;
  float vmax = -3.0e38;
  float t_depth = 0.0;
  bool seen = false; /* t_depth holds the depth event */
  ivec3 visible_block = ivec3(-1); /* the last block found visible */
  int count = int(parts);
  for (int k = 0; k < count; k++) {
    float t = t0 + (float(k) + 0.5) * dt;
    vec3 p = o + t * d;
    ivec3 cell = clamp(ivec3(floor(p + 0.5)), ivec3(0), last_cell);
    if (skip) {
      ivec3 b = cell / block;
      if (b != visible_block) {
        float empty = texelFetch(occupancy, b, 0).r;
        if (empty > 0.5) {
          /* The blocks within empty - 1 of this one are empty: leap to one sample before the
           * first midpoint past their cube (float rounding may leave that one inside: it is
           * tested again). */
          int r = int(empty) - 1;
          vec3 lo = vec3((b - r) * block) - 0.5;
          vec3 hi = min(vec3((b + r + 1) * block), n) - 0.5;
          float exit_t = box_exit(o, d, lo, hi);
          int first_after = int(floor((exit_t - t0) / dt - 0.5)) + 1;
          k = max(k, first_after - 2);
          continue;
        }
        visible_block = b;
      }
    }
    /* (density, weight) summed over the region's voxels among the 8 neighbours: no weight,
     * no part of the sample's part lies in a region cell (those cells are neighbours with
     * weight); all the weight, all of it does (an outside cell would miss its >= 1/8). */
    vec2 rg = sample_region(p, cell, to_texture);
    if (rg.y <= 0.0) {
      continue;
    }
    bool whole = rg.y > 0.99999 && params.labels.x < 0.5;
    vec2 cover = whole ? vec2(1.0, 0.0) : coverage(p - 0.5 * dt * d, p + 0.5 * dt * d);
    if (cover.x <= 0.0) {
      continue;
    }
    float value = rg.x / rg.y;
    float t_front = t + (cover.y - 0.5) * dt;
    if (mode == MODE_XRAY) {
      float mu = params.compositing.z * max(value - params.compositing.w, 0.0);
      tau += mu * part_mm * cover.x;
      if (!seen && mu > 0.0 && mu >= VISIBLE_OPTICAL_DEPTH) {
        seen = true;
        t_depth = t_front;
      }
    }
    else if (mode == MODE_MIP) {
      /* The part's front end, middle and back end (nudged into it), as the CPU ray caster:
       * along a ray parallel to an axis the field is linear between voxel planes. */
      for (int e = -1; e <= 1; e++) {
        float te = t + float(e) * 0.4995 * dt;
        vec3 q = o + te * d;
        if (in_region(ivec3(floor(q + 0.5)))) {
          vec2 qrg = e == 0 ? rg : texture(region, (q + 0.5) * to_texture).rg;
          float qvalue = qrg.x / qrg.y;
          if (qvalue > vmax) {
            vmax = qvalue;
            seen = true;
            t_depth = te;
          }
        }
      }
    }
    else {
      vec4 c = classify(value);
      if (shaded) {
        c.rgb = headlight(c.rgb, texture(gradient, (p + 0.5) * to_texture).xyz / rg.y, towards);
      }
      float alpha = 1.0 - pow(1.0 - c.a, units * cover.x);
      if (!seen && c.a > 0.0 && c.a >= VISIBLE_ALPHA) {
        seen = true;
        t_depth = t_front;
      }
      float weight = (1.0 - acc.a) * alpha;
      acc += vec4(c.rgb * weight, weight);
      if (acc.a >= params.compositing.y) {
        break;
      }
    }
  }
  if (mode == MODE_XRAY) {
    acc = vec4(1.0 - exp(-tau));
  }
  else if (mode == MODE_MIP) {
    if (seen) {
      vec4 c = classify(vmax);
      acc = vec4(c.rgb * c.a, c.a);
      if (!(c.a > 0.0 && c.a >= VISIBLE_ALPHA)) {
        seen = false;
      }
    }
  }
  if (params.image.w > 0.5 && acc.a > 0.0) {
    /* A viewport's display (display_lut.py): the straight colour through the scene's colour
     * management (the table's lattice is cube-root shaped), then into the display-linear space
     * (display value ^ 2.2) where Blender merges the viewport's overlay, premultiplied. */
    vec3 u = pow(clamp(acc.rgb / acc.a, 0.0, 1.0), vec3(1.0 / DISPLAY_SHAPER));
    float n = float(textureSize(display_lut, 0).x);
    vec3 shown = max(texture(display_lut, (u * (n - 1.0) + 0.5) / n).rgb, 0.0);
    acc.rgb = pow(shown, vec3(2.2)) * acc.a;
  }
  out_color = acc;
  if (seen) {
    out_depth = params.clip.z + t_depth;
  }
}

// Colour ramps of the heatmaps drawn over the plan (accuracy planning, analytics).

/** Return the RGB of `u` in [0, 1] on `ramp` (clamped), interpolated between its stops. */
export function rampColour(ramp, u) {
  const s = Math.min(1, Math.max(0, u)) * (ramp.length - 1);
  const i = Math.min(ramp.length - 2, Math.floor(s));
  const f = s - i;
  // c = (1 − f)·c_i + f·c_{i+1}
  return ramp[i].map((a, k) => Math.round((1 - f) * a + f * ramp[i + 1][k]));
}

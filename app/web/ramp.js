// Colour ramps of the heatmaps drawn over the plan (accuracy planning, survey guidance,
// analytics).

// Small errors green, large red (RGB stops, evenly spaced from 0 to the scale's top): the
// accuracy planning overlay and the survey guidance read alike.
export const ERROR_RAMP = [
  [26, 152, 80],
  [145, 207, 96],
  [254, 224, 139],
  [252, 141, 89],
  [215, 48, 39],
];
export const ERROR_ALPHA = 165;
// A cell with no value where one could be (unobservable, unsurveyed): translucent slate.
export const NO_VALUE = [71, 85, 105, 110];

/** Return the CSS gradient of `ramp`, left to right. */
export function rampGradient(ramp) {
  return `linear-gradient(to right, ${ramp.map((c) => `rgb(${c})`).join(",")})`;
}

/** Return the RGB of `u` in [0, 1] on `ramp` (clamped), interpolated between its stops. */
export function rampColour(ramp, u) {
  const s = Math.min(1, Math.max(0, u)) * (ramp.length - 1);
  const i = Math.min(ramp.length - 2, Math.floor(s));
  const f = s - i;
  // c = (1 − f)·c_i + f·c_{i+1}
  return ramp[i].map((a, k) => Math.round((1 - f) * a + f * ramp[i + 1][k]));
}

// The viewer's deviation ramp (mode "deviation"): a face's signed scan-to-model distance (metres; + the scan
// in front of the model) as a diverging colour: blue behind, near-white at 0, red in front, saturating at
// +-DEVIATION_SATURATION_M; grey where the face has no value (no MLS point near, or a LOD parent).
export const DEVIATION_SATURATION_M = 0.10;
export const NO_DEVIATION = [0x9a, 0x9a, 0x9a];
const BEHIND = [0x21, 0x66, 0xac], FRONT = [0xb2, 0x18, 0x2b], ZERO = 0xf7;

export function deviationColour(d) {
  if (d === null || d === undefined || !Number.isFinite(d)) return NO_DEVIATION;
  const t = Math.max(-1, Math.min(1, d / DEVIATION_SATURATION_M));
  const a = Math.abs(t), end = t < 0 ? BEHIND : FRONT;
  return [0, 1, 2].map((k) => Math.round(ZERO + (end[k] - ZERO) * a));
}
